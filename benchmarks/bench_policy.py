"""Training and inference speed of the base flow policy, in one run (issue 3, acceptance 4).

    python benchmarks/bench_policy.py [--store STORE] [--head unet|mlp] [--steps 30] [--json]

Prints, on the Push-T low-dim task (keypoints + agent position): training steps/s, the
sampler's windows/s next to the windows/s that training consumes, and `predict_action` latency
at batch 1 for Euler-1, Euler-10 and RK45 (rtol = atol = 1e-5), each next to one bare forward
pass of the same network (the floor). Latencies are medians after warm-up.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from sefa_data.ingest import IngestOptions, ingest
from sefa_data.sampler import SequenceSampler
from sefa_data.store.zarr_store import EpisodeStore
from sefa_model.config import load_train_config
from sefa_model.policy.artifact import Policy
from sefa_model.train.loop import train

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"


def median_time(fn, repeat: int, warmup: int = 3) -> float:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--store", type=Path, help="a Push-T store (default: import ../shared/data's)")
    ap.add_argument("--head", default="unet", choices=["unet", "mlp"])
    ap.add_argument("--steps", type=int, default=30, help="training steps to time")
    ap.add_argument("--batch", type=int, default=256)
    ap.add_argument("--repeat", type=int, default=20)
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--skip-rk45", action="store_true",
                    help="leave out RK45 (slow on CPU for the 65 M-parameter U-Net)")
    ap.add_argument("--checkpoint", type=Path,
                    help="measure predict_action on this trained policy (default: the short run's)")
    args = ap.parse_args()
    torch.set_num_threads(torch.get_num_threads())

    with tempfile.TemporaryDirectory() as tmp:
        store = args.store
        if store is None:
            store = Path(tmp) / "pusht.zarr"
            ingest([SHARED / "pusht_cchi_v7_replay.zarr"], store,
                   IngestOptions(fps=10, keys=["keypoint", "state", "action"]))
        overrides = ["shape_meta.obs.keypoint.type=low_dim", "shape_meta.obs.state.dims=[0,2]",
                     f"policy.head={args.head}", f"training.batch_size={args.batch}",
                     f"training.max_steps={args.steps}", f"training.val_every={10 ** 9}",
                     f"training.checkpoint_every={args.steps}", "training.val_batches=1"]
        run = Path(tmp) / "run"
        t = time.perf_counter()
        step_times = []
        last = [time.perf_counter()]

        def on_step(step, total, loss):
            now = time.perf_counter()
            step_times.append(now - last[0])
            last[0] = now

        from sefa_model.train.loop import Callbacks

        train(load_train_config(None, overrides), run, store, callbacks=Callbacks(on_step=on_step))
        steps_per_s = 1.0 / statistics.median(step_times[3:] or step_times)
        setup_s = time.perf_counter() - t - sum(step_times)

        sampler = SequenceSampler(EpisodeStore.open(store), 16, 2, 8, obs_keys=["keypoint", "state"])
        rng = np.random.default_rng(0)
        batch_s = median_time(lambda: sampler.batch(rng.integers(0, len(sampler), args.batch)), args.repeat)
        windows_per_s = args.batch / batch_s

        policy = Policy.load(args.checkpoint or run)
        obs = sampler.batch(np.array([len(sampler) // 2]))
        obs = {"keypoint": obs["keypoint"], "state": obs["state"]}
        model = policy.model
        o = policy.prepare_obs(obs)
        x = torch.randn(1, 16, 2)
        tt = torch.full((1,), 0.5)
        with torch.no_grad():
            forward_s = median_time(lambda: model.velocity(x, tt, model.encode(o)), args.repeat * 5)
        rows = []
        settings = [("Euler-1", "euler", 1), ("Euler-10", "euler", 10)]
        if not args.skip_rk45:
            settings.append(("RK45 1e-5", "rk45", None))
        for name, solver, steps in settings:
            nfe = policy.predict_action(obs, solver=solver, steps=steps).nfe
            # an adaptive solve can take hundreds of evaluations: fewer repeats keep it short
            reps = args.repeat if nfe <= 20 else max(3, args.repeat // 5)
            s = median_time(lambda: policy.predict_action(obs, solver=solver, steps=steps), reps,
                            warmup=1)
            rows.append({"solver": name, "nfe": nfe, "latency_ms": s * 1e3,
                         "x_forward": s / forward_s})
    params = sum(p.numel() for p in model.parameters())
    out = {"machine": f"{platform.machine()}, {torch.get_num_threads()} torch threads, "
                      f"torch {torch.__version__}, device cpu",
           "head": args.head, "params": params, "batch": args.batch,
           "train_steps_per_s": steps_per_s, "train_windows_per_s": steps_per_s * args.batch,
           "train_setup_s": setup_s, "sampler_windows_per_s": windows_per_s,
           "forward_ms": forward_s * 1e3, "predict_action": rows}
    if args.json:
        print(json.dumps(out, indent=2))
        return
    print(f"base flow policy, Push-T low-dim, {out['machine']}")
    print(f"latency measured on {args.checkpoint or 'the short training run'} ({params / 1e6:.1f} M params)")
    print(f"training: {steps_per_s:.2f} steps/s at batch {args.batch} = {steps_per_s * args.batch:.0f} windows/s consumed")
    print(f"sampler:  {windows_per_s:.0f} windows/s ({windows_per_s / (steps_per_s * args.batch):.0f}x what training consumes)")
    print(f"bare forward pass (encoder + head, batch 1): {forward_s * 1e3:.2f} ms")
    print(f"{'predict_action batch 1':24s} {'NFE':>5s} {'ms':>9s} {'x forward':>10s}")
    for r in rows:
        print(f"{r['solver']:24s} {r['nfe']:5d} {r['latency_ms']:9.2f} {r['x_forward']:10.1f}")


if __name__ == "__main__":
    main()
