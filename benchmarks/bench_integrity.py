"""What the checkpoint checks of issue 23 cost at load: the checksums (SHA-256 of every file) and
the finiteness scan of the weights, against the whole `Policy.load`, in one process.

    PYTHONPATH=. python benchmarks/bench_integrity.py [--repeats 20] [--json]

On the real Push-T low-dim store (../shared/data, ingested into a temporary folder) it trains two
policies for one step (the timing does not depend on the weights' values): the deployment tests'
small MLP and the default U-Net head. For each it prints the checkpoint's size, the median time
of `Policy.load`, of the checksums it verifies (the files a policy reads, not the optimizer
state) and of the finiteness scan, their share of the load, the checksums of every file (what a
resumed run verifies), and a one-step `predict_action` call for scale (the checks run once per
load, not per call).
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
PUSHT = REPO.parent / "shared" / "data" / "pusht_cchi_v7_replay.zarr"
LOWDIM = ["shape_meta.obs.keypoint.type=low_dim", "shape_meta.obs.state.dims=[0,2]",
          "training.max_steps=1", "training.val_every=1", "training.val_sample_windows=2",
          "training.val_batches=1", "training.batch_size=8"]
POLICIES = {"mlp (tests' tiny policy)": ["policy.head=mlp", "policy.mlp_hidden_dims=[64,64]",
                                         "policy.time_embed_dim=32"],
            "unet (default head)": []}


READ_BY_LOAD = ["config.json", "ema.safetensors", "normalizer.json", "normalizer.safetensors",
                "processor.json"]


def median_ms(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        fn()
        times.append(time.perf_counter() - started)
    return 1e3 * statistics.median(times)


def measure(ckpt: Path, repeats: int) -> dict:
    import numpy as np
    import torch

    from sefa_model.policy.checkpoint import non_finite, read_tensors, verify_checksums
    from sefa_model.policy.artifact import Policy

    policy = Policy.load(ckpt, device="cpu")
    size = sum(p.stat().st_size for p in ckpt.rglob("*") if p.is_file())
    ema = read_tensors(ckpt / "ema.safetensors")
    obs = {k: np.zeros((1, policy.cfg.policy.n_obs_steps, *spec.frame_shape), np.float32)
           for k, spec in policy.cfg.shape_meta.obs.items()}
    noise = torch.zeros(1, policy.cfg.policy.horizon, policy.cfg.shape_meta.action.shape[-1])
    row = {"checkpoint_mb": size / 2**20,
           "load_ms": median_ms(lambda: Policy.load(ckpt, device="cpu"), repeats),
           # what Policy.load hashes (sefa_model/policy/checkpoint.py: open_policy), and everything (a
           # resumed run: the optimizer state too)
           "checksums_ms": median_ms(lambda: verify_checksums(ckpt, READ_BY_LOAD), repeats),
           "checksums_all_ms": median_ms(lambda: verify_checksums(ckpt), repeats),
           "finite_scan_ms": median_ms(lambda: non_finite(ema), repeats),
           "one_step_call_ms": median_ms(lambda: policy.predict_action(
               obs, solver="euler", steps=1, noise=noise), repeats * 5)}
    row["checks_share_of_load"] = (row["checksums_ms"] + row["finite_scan_ms"]) / row["load_ms"]
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    if not PUSHT.exists():
        sys.exit(f"needs {PUSHT} (../shared/data)")
    import torch

    from sefa_data.ingest import IngestOptions, ingest
    from sefa_model.config import load_train_config
    from sefa_model.train.loop import train

    torch.set_num_threads(1)
    rows = {}
    with tempfile.TemporaryDirectory(prefix="sefa-integrity-") as tmp:
        store = Path(tmp) / "pusht.zarr"
        ingest([PUSHT], store, IngestOptions(fps=10, keys=["keypoint", "state", "action"]))
        for name, extra in POLICIES.items():
            run = Path(tmp) / name.split()[0]
            train(load_train_config(None, LOWDIM + extra), run, store)
            rows[name] = measure(run / "checkpoints" / "latest", args.repeats)
    if args.json:
        print(json.dumps(rows, indent=2))
        return
    print(f"{'policy':26} {'MB':>7} {'load ms':>8} {'sha256 ms':>9} {'finite ms':>9} "
          f"{'checks/load':>11} {'sha256 all ms':>13} {'1-step call ms':>14}")
    for name, r in rows.items():
        print(f"{name:26} {r['checkpoint_mb']:7.2f} {r['load_ms']:8.2f} {r['checksums_ms']:9.2f} "
              f"{r['finite_scan_ms']:9.2f} {r['checks_share_of_load']:11.0%} "
              f"{r['checksums_all_ms']:13.2f} {r['one_step_call_ms']:14.3f}")


if __name__ == "__main__":
    main()
