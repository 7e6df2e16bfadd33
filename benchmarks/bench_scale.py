"""The GPU check's table, measured in one run on one device:

    python benchmarks/bench_scale.py [--device auto] [--quick] [--out docs/gpu_check.md]

- training steps/s at batch 256 for the MLP head and Diffusion Policy's U-Net (Push-T low-dim);
- the input pipeline: loader windows/s (DataLoader workers building whole steps, pinned memory)
  next to the windows/s one training step consumes, for low-dim keys and for 96x96 images;
- reflow couplings/s (K = 10, RK45 rtol = atol = 1e-5) of the trained MLP flow, on a GPU with
  its velocity field replayed as a CUDA graph and eager, beside the floor: the same number of
  network evaluations alone;
- batch-1 predict_action latency of base RK45, DDPM-100, DDIM-10 and a one-step policy (the
  trained flow at Euler-1 stands in for the SeFA student: the same network and one evaluation).

Beside every training rate, the limit: the bare step of the same network (forward, backward,
clip, AdamW on random tensors already on the device, no data, no EMA, no bookkeeping) timed in
the same process, and the loop's ratio to it; beside the one-step latency, the bare forward
(replayed as a CUDA graph on a GPU). `--acceptance` measures only what the GPU work is judged
by (scripts/gpu_pace.sh): the MLP and U-Net loops against their bare steps, eager and
compiled, bf16 and fp32 (whether bf16 pays for a network this small), one-step predict_action
captured and eager, its served round trip, and reflow couplings/s.

Everything is built from ../shared/data's Push-T demonstrations in a temporary workspace. On a
GPU the table names it; on a CPU (`--quick`) the same rows run at a small budget.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from datetime import date
from pathlib import Path

import numpy as np
import torch

from sefa_data.ingest import IngestOptions, ingest
from sefa_data.store.zarr_store import EpisodeStore
from sefa_model.config import load_train_config
from sefa_model.distributed import DistContext, describe, resolve_device
from sefa_model.eval.latency import bench_latency
from sefa_model.policy.artifact import Policy
from sefa_model.sefa.reflow import CouplingConfig, generate_couplings
from sefa_model.data.windows import PolicyData
from sefa_model.train.batches import ExpertPairs, loader_workers, step_batches
from sefa_model.train.loop import Callbacks, train
from sefa_model.policy.model import resolve_shapes

# the real recordings beside the checkout; a GPU machine's session links a copy there
# (scripts/gpu_session.sh)
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


def sync_of(device: str):
    return torch.cuda.synchronize if device.startswith("cuda") else (lambda: None)


def bare_steps_per_s(store: Path, overrides: list[str], device: str, steps: int) -> float:
    """The floor of a training step: the loop's network, loss, clip and AdamW (fused on CUDA,
    as a hand-written fast loop would use) at the loop's batch, precision and compile setting,
    on random tensors of its inputs' shapes already on the device."""
    from sefa_model.distributed import bf16_supported
    from sefa_model.policy.model import FlowPolicyModel
    from sefa_model.methods import StepCalls, Times, method_of

    cfg = resolve_shapes(load_train_config(None, overrides + [f"training.device={device}",
                                                              "training.batch_size=256"]),
                         EpisodeStore.open(store))
    dev, t_cfg = torch.device(device), cfg.training
    data = PolicyData(cfg, EpisodeStore.open(store), None)
    data.use_normalizer(data.fit_normalizer())
    obs, x1 = data.tensors(data.train, np.arange(t_cfg.batch_size) % len(data.train), dev)
    torch.manual_seed(0)
    obs = {k: torch.randn_like(v) for k, v in obs.items()}
    x0, x1 = torch.randn_like(x1), torch.randn_like(x1)
    method = method_of(cfg)  # the loop's loss and times
    times = method.draw(cfg, len(x1), torch.Generator().manual_seed(0))
    times = Times(times.t.to(dev), None if times.d is None else times.d.to(dev))
    model = FlowPolicyModel(cfg).to(dev)
    opt = torch.optim.AdamW(model.parameters(), lr=t_cfg.lr, betas=tuple(t_cfg.betas),
                            eps=t_cfg.eps, weight_decay=t_cfg.weight_decay,
                            **({"fused": True} if dev.type == "cuda" else {}))
    forward = model
    if t_cfg.compile:
        forward = torch.compile(model, mode="reduce-overhead" if dev.type == "cuda" else None)
    autocast = t_cfg.mixed_precision and bf16_supported(dev)
    calls = StepCalls(lambda x, t, d=None: forward(obs, x, t) if d is None else forward(obs, x, t, d))

    def step():
        with torch.autocast(dev.type, dtype=torch.bfloat16, enabled=autocast):
            loss = method.loss(cfg, calls, x0, x1, times)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        if t_cfg.grad_clip:
            torch.nn.utils.clip_grad_norm_(model.parameters(), t_cfg.grad_clip)
        opt.step()
    sync = sync_of(device)
    for _ in range(max(3, steps // 5)):  # as the loop's rate: warm-up, allocator, compile
        step()
    sync()
    started = time.perf_counter()
    for _ in range(steps - steps // 5):
        step()
    sync()
    return (steps - steps // 5) / (time.perf_counter() - started)


def loop_and_bare(store: Path, run: Path, overrides: list[str], device: str, steps: int,
                  rounds: int = 1) -> tuple[float, float]:
    """(sefa's loop, the bare step) in steps/s, in this process, taking turns `rounds` times
    and keeping each one's best (a shared machine's slow spell then hits both alike)."""
    loop, bare = 0.0, 0.0
    for r in range(rounds):
        bare = max(bare, bare_steps_per_s(store, overrides, device, steps))
        loop = max(loop, steps_per_s(store, run / f"round{r}", overrides, device, steps))
    return loop, bare


def latency_rows(policy_dir: Path, store: Path, device: str, calls: int) -> list[tuple[str, float]]:
    """One-step predict_action (Euler-1, batch 1, synchronised) as served: captured as a CUDA
    graph on a GPU (the default there), eager beside it, and the bare forward's floor: one
    network evaluation, replayed as a CUDA graph on a GPU."""
    from sefa_model.eval.latency import example_observation, percentiles_ms, time_calls

    policy = Policy.load(policy_dir, device=device)
    eager = Policy.load(policy_dir, device=device)
    eager.capture = False
    obs, _ = example_observation(policy, store)
    noise = torch.randn(1, policy.cfg.policy.horizon, policy.cfg.shape_meta.action.shape[-1],
                        generator=torch.Generator().manual_seed(0))
    o = policy.prepare_obs(obs)
    x, t = noise.to(policy.device), torch.zeros(1, device=policy.device)
    forward = lambda: policy.model(o, x, t)  # noqa: E731
    if policy.device.type == "cuda":
        from sefa_model.flow.cuda_graphs import CapturedCall

        with torch.inference_mode():
            graph = CapturedCall(lambda oo, xx: policy.model(oo, xx, t), o, x)
        forward = lambda: graph(o, x)  # noqa: E731
    run = {"captured": lambda: policy.predict_action(obs, solver="euler", steps=1, noise=noise),
           "eager": lambda: eager.predict_action(obs, solver="euler", steps=1, noise=noise),
           "forward": forward}
    with torch.inference_mode():
        times = time_calls(run, warmup=20, calls=calls, max_seconds=20, sync=sync_of(device),
                           warmup_seconds=1.0)
    p50 = {k: percentiles_ms(v)[0] for k, v in times.items()}
    graphed = policy.device.type == "cuda"
    return [(f"predict_action p50 ms, one-step (Euler-1){', CUDA graph (the default)' if graphed else ''}",
             p50["captured"]),
            (f"predict_action p50 ms, one-step (Euler-1), eager", p50["eager"]),
            (f"  bare forward p50 ms{', CUDA graph' if graphed else ''} (the floor)", p50["forward"]),
            ("  predict_action / bare forward", p50["captured"] / p50["forward"])]


def served_rows(policy_dir: Path, store: Path, calls: int) -> list[tuple[str, float]]:
    """The one-step policy through `sefa serve` on loopback (the server on the same device)."""
    from sefa_deploy.bench import bench_round_trip
    from sefa_model.eval.latency import example_observation

    policy = Policy.load(policy_dir)
    obs, _ = example_observation(policy, store)
    noise = np.random.default_rng(0).standard_normal(
        (policy.cfg.policy.horizon, policy.cfg.shape_meta.action.shape[-1])).astype(np.float32)
    out = bench_round_trip(policy_dir, solver="euler", steps=1, obs={k: v[0] for k, v in obs.items()},
                           noise=noise, calls=calls, warmup=20, max_seconds=20,
                           label="one-step (Euler-1)")
    return [("served round trip p50 ms, one-step (loopback)", out["rows"][1]["p50_ms"]),
            ("  served minus in-process p50 ms", out["added_p50_ms"])]


def train_rows(name: str, store: Path, run: Path, overrides: list[str], device: str, steps: int,
               rounds: int) -> list[tuple[str, float]]:
    loop, bare = loop_and_bare(store, run, overrides, device, steps, rounds)
    return [(f"train steps/s, {name}, batch 256", loop),
            (f"  bare step steps/s, {name} (the floor)", bare),
            (f"  loop / bare, {name}", loop / bare)]


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
    ap.add_argument("--acceptance", action="store_true",
                    help="only the rows the GPU work is judged by (scripts/gpu_pace.sh)")
    ap.add_argument("--only", nargs="+", choices=PARTS,
                    help="with --acceptance: these parts (train: eager training rows; compiled: "
                         "the torch.compile rows, minutes of compiling on a GPU)")
    ap.add_argument("--steps", type=int, help="training steps per timing (default by device)")
    ap.add_argument("--rounds", type=int, default=1, help="loop and bare timed in turns, best of")
    args = ap.parse_args()
    device = resolve_device(args.device)
    dev = str(device) if device.type != "cuda" else "cuda"
    quick = args.quick or device.type == "cpu"
    n_steps = args.steps or (30 if quick else 300)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        store = tmp / "pusht.zarr"
        ingest([SHARED / "pusht_cchi_v7_replay.zarr"], store,
               IngestOptions(fps=10, keys=["keypoint", "state", "action"] if args.acceptance else None))
        mlp = LOWDIM + ["policy.head=mlp", "training.lr=1e-3"]
        mlp_steps = args.steps or (n_steps * 10 if not quick else n_steps)
        unet_steps = args.steps or max(10, n_steps // 3 if quick else n_steps)
        if args.acceptance:
            rows = acceptance(store, tmp, mlp, dev, mlp_steps, unet_steps, quick, args.only,
                              args.rounds)
        else:
            rows = table_rows(store, tmp, mlp, device, dev, mlp_steps, unet_steps, quick,
                              args.rounds)
    report(rows, device, args)


def table_rows(store: Path, tmp: Path, mlp: list[str], device: torch.device, dev: str,
               mlp_steps: int, unet_steps: int, quick: bool, rounds: int) -> list:
    """`make gpu-check`'s table."""
    rows = train_rows("MLP head", store, tmp / "mlp", mlp, dev, mlp_steps, rounds)
    rows += train_rows("DP U-Net", store, tmp / "unet", LOWDIM, dev, unet_steps, rounds)
    has_images = "img" in EpisodeStore.open(store).keys()
    for name, ov in (("low-dim", LOWDIM), ("96x96 image + state", IMAGE)):
        if ov is IMAGE and not has_images:  # a GPU machine's copy of Push-T may leave them out
            print("bench_scale: the Push-T store here has no images: no image loader row")
            continue
        rate, workers = loader_windows_per_s(store, ov, device, 20 if quick else 100)
        rows.append((f"loader windows/s, {name} ({workers} workers)", rate))
    rows.append(("train windows/s consumed, MLP (= steps/s x 256)", rows[0][1] * 256))
    rows.append(("train windows/s consumed, U-Net (= steps/s x 256)", rows[3][1] * 256))
    ddpm = tmp / "ddpm"
    train(load_train_config(None, mlp + ["objective=ddpm", "training.max_steps=5",
                                         "training.val_every=50", f"training.device={dev}"]),
          ddpm, store)
    mlp_run = tmp / "mlp" / "round0"
    rows += reflow_rows(mlp_run, store, dev, quick)
    lat = bench_latency([f"{mlp_run}@rk45", f"{ddpm}@ddpm-100", f"{ddpm}@ddim-10"],
                        store=store, device=dev, calls=50 if quick else 200, warmup=10,
                        max_seconds=10)
    names = ["base flow RK45", "DDPM-100", "DDIM-10"]
    for name, r in zip(names, lat["rows"]):
        rows.append((f"predict_action p50 ms, {name} (NFE {r['nfe']}; forward "
                     f"{r['forward_ms']:.3f} ms)", r["p50_ms"]))
    rows += latency_rows(mlp_run, store, dev, 50 if quick else 200)
    return rows


def reflow_rows(run: Path, store: Path, dev: str, quick: bool) -> list[tuple[str, float]]:
    """Reflow couplings/s (K = 10, RK45 1e-5) with the velocity field replayed as a CUDA graph
    (the default on a GPU) and eager (the path before it, on the same GPU in this process), and
    the floor: the couplings/s of the solves' network evaluations alone, each timed as one
    replayed (on a CPU, eager) evaluation of the field at a whole block's rows."""
    policy = Policy.load(run, device=dev)
    cfg = CouplingConfig(max_windows=256 if quick else 2048)
    runs = {"CUDA graphs (the default)": True, "eager": False} if dev == "cuda" else {"": False}
    if dev == "cuda":  # the first solves on a fresh GPU pay its start (cuBLAS, allocator): untimed
        generate_couplings(policy, store, run.parent / "warmup.zarr",
                           CouplingConfig(max_windows=cfg.batch_windows), capture=False)
    rows = []
    for i, (name, capture) in enumerate(runs.items()):
        summary = generate_couplings(policy, store, run.parent / f"couplings{i}.zarr", cfg,
                                     capture=capture)
        rows.append((f"reflow couplings/s (K=10, RK45 1e-5, {summary['nfe_per_solve']:.0f} "
                     "NFE/solve)" + (f", {name}" if name else ""), summary["couplings_per_s"]))
    # summary["nfe"]: the calls of the network over every solve
    floor = summary["n"] / (field_eval_seconds(policy, cfg, store, dev) * summary["nfe"])
    rows.append(("  floor: the network evaluations alone, couplings/s", floor))
    rows.append(("  reflow / floor", rows[0][1] / floor))
    return rows


def field_eval_seconds(policy: Policy, cfg: CouplingConfig, store: Path, dev: str) -> float:
    """Seconds of one evaluation of the velocity field at a block's batch_windows * K rows (the
    last block may be smaller: this is the upper bound), replayed as a CUDA graph on a GPU."""
    from sefa_model.flow.cuda_graphs import FieldGraphs
    from sefa_model.eval.latency import time_calls

    rows = cfg.batch_windows * cfg.samples_per_window
    d = policy.cfg.shape_meta.action.shape[-1]
    gen = torch.Generator().manual_seed(0)
    x = torch.randn(rows, policy.cfg.policy.horizon, d, generator=gen).to(policy.device)
    t = torch.rand(rows, generator=gen).to(policy.device)
    data = PolicyData(policy.cfg, EpisodeStore.open(store), policy.normalizer)
    with torch.no_grad():
        obs, _ = data.tensors(data.train, np.arange(cfg.batch_windows) % len(data.train),
                              policy.device)
        cond = policy.model.encode(obs).repeat_interleave(cfg.samples_per_window, dim=0)
        field = policy.model.velocity
        if dev == "cuda":
            field = FieldGraphs().field(field)
        times = time_calls({"field": lambda: field(x, t, cond)}, warmup=5, calls=50,
                           max_seconds=10, sync=sync_of(dev))
    return float(np.median(times["field"]))


PARTS = ("train", "compiled", "serve", "reflow")


def acceptance(store: Path, tmp: Path, mlp: list[str], dev: str, mlp_steps: int,
               unet_steps: int, quick: bool, only: list[str] | None, rounds: int) -> list:
    """The GPU work's acceptance rows (see the module docstring), each beside its floor; `only`
    some of PARTS (a GPU session may have to split them over calls)."""
    parts, rows = set(only or PARTS), []
    if "train" in parts:
        rows += train_rows("MLP head", store, tmp / "mlp", mlp, dev, mlp_steps, rounds)
        if dev != "cpu":  # bf16 autocast is a GPU setting: the CPU trains in fp32 either way
            rows += train_rows("MLP head, fp32", store, tmp / "mlp32",
                               mlp + ["training.mixed_precision=false"], dev, mlp_steps, rounds)
        rows += train_rows("DP U-Net", store, tmp / "unet", LOWDIM, dev, unet_steps, rounds)
    if "compiled" in parts and not quick:  # compiling costs minutes on a CPU, which runs eager
        compiled = ["training.compile=true"]
        rows += train_rows("MLP head, compiled", store, tmp / "mlpc", mlp + compiled, dev,
                           mlp_steps, rounds)
        rows += train_rows("DP U-Net, compiled", store, tmp / "unetc", LOWDIM + compiled, dev,
                           unet_steps, rounds)
    if "serve" in parts:
        run = tmp / "mlp" / "round0"
        if not run.exists():
            train(load_train_config(None, mlp + ["training.max_steps=30", "training.val_every=30",
                                                 f"training.device={dev}"]), run, store)
        rows += latency_rows(run, store, dev, 50 if quick else 500)
        rows += served_rows(run, store, 50 if quick else 500)
    if "reflow" in parts:
        run = tmp / "reflow_base"
        train(load_train_config(None, mlp + ["training.max_steps=30", "training.val_every=30",
                                             f"training.device={dev}"]), run, store)
        rows += reflow_rows(run, store, dev, quick)
    return rows


def report(rows: list, device: torch.device, args) -> None:
    where = describe(device)
    if args.json:
        print(json.dumps({"device": where, "date": str(date.today()), "rows": rows}, indent=2))
    flags = "".join(f" {a}" for a in sys.argv[1:] if a not in ("--json",))
    table = [f"Measured on {where}, {date.today()} (`python benchmarks/bench_scale.py{flags}`):",
             "", "| measurement | value |", "|---|---|"]
    table += [f"| {name} | {value:,.{3 if abs(value) < 10 else 2}f} |" for name, value in rows]
    text = "\n".join(table) + "\n"
    print(text)
    if args.out:
        write_table(args.out, text)


TABLE_BEGIN = "<!-- the latest table of benchmarks/bench_scale.py --out: rewritten by each run -->"
TABLE_END = "<!-- end of the latest table -->"


def write_table(path: Path, text: str) -> None:
    """Put the table into `path` between its markers, leaving the rest of the page (what earlier
    runs found, written by hand) as it is; a page without them gets them after its title, a
    missing page is made with the title "GPU check"."""
    block = f"{TABLE_BEGIN}\n{text}{TABLE_END}\n"
    page = path.read_text() if path.exists() else "# GPU check\n"
    if TABLE_BEGIN in page and TABLE_END in page:
        start, end = page.index(TABLE_BEGIN), page.index(TABLE_END) + len(TABLE_END) + 1
        page = page[:start] + block + page[end:]
    else:
        title, _, rest = page.partition("\n")
        page = f"{title}\n\n{block}" + (f"\n{rest.lstrip(chr(10))}" if rest.strip() else "")
    path.write_text(page)


if __name__ == "__main__":
    main()
