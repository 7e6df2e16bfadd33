"""The GPU check's table (issue 10), measured in one run on one device:

    python benchmarks/bench_scale.py [--device auto] [--quick] [--out docs/gpu_check.md]

- training steps/s at batch 256 for the MLP head and Diffusion Policy's U-Net (Push-T low-dim);
- the input pipeline: loader windows/s (DataLoader workers building whole steps, pinned memory)
  next to the windows/s one training step consumes, for low-dim keys and for 96x96 images;
- reflow couplings/s (K = 10, RK45 rtol = atol = 1e-5) of the trained MLP flow;
- batch-1 predict_action latency of base RK45, DDPM-100, DDIM-10 and a one-step policy (the
  trained flow at Euler-1 stands in for the SeFA student: the same network and one evaluation).

Everything is built from ../shared/data's Push-T demonstrations in a temporary workspace. On a
GPU the table names it; on a CPU (`--quick`) the same rows run at a small budget.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from datetime import date
from pathlib import Path

import numpy as np
import torch

from sefa_data.ingest import IngestOptions, ingest
from sefa_data.zarr_store import EpisodeStore
from sefa_model.config import load_train_config
from sefa_model.distributed import DistContext, describe, resolve_device
from sefa_model.latency import bench_latency
from sefa_model.policy import Policy
from sefa_model.reflow import CouplingConfig, generate_couplings
from sefa_model.policy_data import PolicyData
from sefa_model.train_batches import ExpertPairs, loader_workers, step_batches
from sefa_model.training import Callbacks, train
from sefa_model.flow_policy import resolve_shapes

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
LOWDIM = ["shape_meta.obs.keypoint.type=low_dim", "shape_meta.obs.state.dims=[0,2]"]
IMAGE = ["shape_meta.obs.img.type=rgb", "shape_meta.obs.state.dims=[0,2]",
         "policy.crop_shape=[84,84]"]


def steps_per_s(store: Path, run: Path, overrides: list[str], device: str, steps: int) -> float:
    """Optimizer steps/s after the first 20% of the steps (warm-up, allocator, compile)."""
    stamps: dict[int, float] = {}
    cfg = load_train_config(None, overrides + [f"training.max_steps={steps}", f"training.device={device}",
                                               f"training.val_every={10 * steps}",
                                               f"training.checkpoint_every={10 * steps}",
                                               f"training.log_every={steps}", "training.batch_size=256"])
    sync = torch.cuda.synchronize if device.startswith("cuda") else (lambda: None)

    def on_step(step, total, loss):
        if step in (steps // 5, steps):
            sync()
            stamps[step] = time.perf_counter()
    train(cfg, run, store, callbacks=Callbacks(on_step=on_step))
    return (steps - steps // 5) / (stamps[steps] - stamps[steps // 5])


def loader_windows_per_s(store: Path, overrides: list[str], device: torch.device, steps: int) -> tuple[float, int]:
    cfg = resolve_shapes(load_train_config(None, overrides + ["training.batch_size=256"]), EpisodeStore.open(store))
    data = PolicyData(cfg, EpisodeStore.open(store), None)
    workers = loader_workers(None, device, DistContext())
    cfg.training.max_steps = steps
    started = time.perf_counter()
    n = sum(len(b["x0"]) for b in step_batches(ExpertPairs(data), cfg, 0, slice(0, 256), device, workers))
    return n / (time.perf_counter() - started), workers


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="auto")
    ap.add_argument("--quick", action="store_true", help="a CPU-sized budget")
    ap.add_argument("--out", type=Path, help="write the table as markdown here")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    device = resolve_device(args.device)
    dev = str(device) if device.type != "cuda" else "cuda"
    quick = args.quick or device.type == "cpu"
    n_steps = 30 if quick else 300
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        store = tmp / "pusht.zarr"
        ingest([SHARED / "pusht_cchi_v7_replay.zarr"], store, IngestOptions(fps=10))
        mlp = LOWDIM + ["policy.head=mlp", "training.lr=1e-3"]
        rows.append(("train steps/s, MLP head, batch 256", steps_per_s(store, tmp / "mlp", mlp, dev, n_steps * 10 if not quick else n_steps)))
        rows.append(("train steps/s, DP U-Net, batch 256", steps_per_s(store, tmp / "unet", LOWDIM, dev, max(10, n_steps // 3 if quick else n_steps))))
        for name, ov in (("low-dim", LOWDIM), ("96x96 image + state", IMAGE)):
            rate, workers = loader_windows_per_s(store, ov, device, 20 if quick else 100)
            rows.append((f"loader windows/s, {name} ({workers} workers)", rate))
        rows.append(("train windows/s consumed, MLP (= steps/s x 256)", rows[0][1] * 256))
        rows.append(("train windows/s consumed, U-Net (= steps/s x 256)", rows[1][1] * 256))
        ddpm = tmp / "ddpm"
        train(load_train_config(None, mlp + ["objective=ddpm", "training.max_steps=5", "training.val_every=50",
                                             f"training.device={dev}"]), ddpm, store)
        policy = Policy.load(tmp / "mlp", device=dev)
        summary = generate_couplings(policy, store, tmp / "couplings.zarr",
                                     CouplingConfig(max_windows=256 if quick else 2048))
        rows.append((f"reflow couplings/s (K=10, RK45 1e-5, {summary['nfe_per_solve']:.0f} NFE/solve)",
                     summary["couplings_per_s"]))
        lat = bench_latency([f"{tmp}/mlp@rk45", f"{ddpm}@ddpm-100", f"{ddpm}@ddim-10", f"{tmp}/mlp@euler-1"],
                            store=store, device=dev, calls=50 if quick else 200, warmup=10,
                            max_seconds=10)
        names = ["base flow RK45", "DDPM-100", "DDIM-10", "one-step (Euler-1)"]
        for name, r in zip(names, lat["rows"]):
            rows.append((f"predict_action p50 ms, {name} (NFE {r['nfe']}; forward {r['forward_ms']:.3f} ms)", r["p50_ms"]))
    where = describe(device)
    if args.json:
        print(json.dumps({"device": where, "date": str(date.today()), "rows": rows}, indent=2))
    table = [f"Measured on {where}, {date.today()} (`python benchmarks/bench_scale.py"
             f"{' --quick' if args.quick else ''}`):", "", "| measurement | value |", "|---|---|"]
    table += [f"| {name} | {value:,.2f} |" for name, value in rows]
    text = "\n".join(table) + "\n"
    print(text)
    if args.out:
        args.out.write_text(f"# GPU check\n\n{text}")


if __name__ == "__main__":
    main()
