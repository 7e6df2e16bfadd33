"""Reflow coupling generation vs the reference approach, in one run (issue: reflow, acceptance).

    python benchmarks/bench_reflow.py [--workspace DIR | --checkpoint CKPT --store STORE]
                                      [--windows 128] [--samples 10] [--ref-batch 64]
                                      [--rtol 1e-5] [--atol 1e-5] [--json]

Same model, same training windows, same tolerance, measured side by side:

- ours: `sefa_model.reflow.generate_couplings`, which encodes each window once, repeats it K
  times and integrates every chunk of a block as ONE batched torch RK45 solve; timed with
  batch_windows = N (one solve of N*K chunks) and batch_windows = --ref-batch;
- reference (SeFA's gen_data): for each dataloader batch of --ref-batch windows and for each of
  the K samples separately, the batch is flattened into one float64 numpy vector and integrated
  by `scipy.integrate.solve_ivp(method="RK45")`, the velocity network evaluated under
  torch.no_grad on the CPU at every call (numpy -> torch -> numpy).

Prints couplings/s, total NFE and the speedup over the reference, plus the agreement of the
generated chunks: the reference is started from exactly the noise that ours used (read back
from the couplings written by the batch_windows = N run), so the mean |difference| is solver
error only (both solves share one step size across a batch, but the batches differ).

Without --checkpoint/--store, a Push-T low-dim store is imported from ../shared/data and a
small MLP base policy is trained for --train-steps steps (so the velocity field is a realistic,
trained one); with --workspace DIR those are kept in DIR (DIR/dataset.zarr, DIR/train) and
reused on the next run.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np
import scipy
import torch
import zarr
from scipy.integrate import solve_ivp

from sefa_data.ingest import IngestOptions, ingest
from sefa_data.zarr_store import EpisodeStore
from sefa_model.config import load_train_config
from sefa_model.policy import Policy
from sefa_model.reflow import CouplingConfig, generate_couplings, window_subset
from sefa_model.training import PolicyData, train

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"

PUSHT_LOWDIM = [
    "shape_meta.obs.keypoint.type=low_dim",
    "shape_meta.obs.state.dims=[0,2]",
    "policy.head=mlp", "policy.mlp_hidden_dims=[256,256,256]", "policy.time_embed_dim=64",
    "training.batch_size=256", "training.lr=1e-3", "training.lr_warmup_steps=50",
    "training.val_batches=2", "training.val_sample_windows=128", "training.log_every=50",
]


def build(workdir: Path, train_steps: int) -> tuple[Path, Path]:
    """(checkpoint, store) in `workdir`, imported and trained unless already there."""
    store, run = workdir / "dataset.zarr", workdir / "train"
    if not (store / ".zgroup").exists():
        ingest([SHARED / "pusht_cchi_v7_replay.zarr"], store,
               IngestOptions(fps=10, keys=["keypoint", "state", "action"]))
    if not (run / "checkpoints" / "latest" / "config.json").exists():
        cfg = load_train_config(None, PUSHT_LOWDIM + [f"training.max_steps={train_steps}",
                                                      f"training.val_every={train_steps}",
                                                      f"training.checkpoint_every={train_steps}"])
        train(cfg, run, store)
    return run, store


def run_ours(policy: Policy, store: Path, out: Path, n: int, k: int, batch_windows: int,
             rtol: float, atol: float) -> tuple[dict, np.ndarray, np.ndarray, np.ndarray]:
    cfg = CouplingConfig(samples_per_window=k, solver="rk45", rtol=rtol, atol=atol,
                         batch_windows=batch_windows, max_windows=n, seed=0)
    if policy.device.type == "cuda":
        torch.cuda.synchronize()
    t = time.perf_counter()
    summary = generate_couplings(policy, store, out, cfg)
    if policy.device.type == "cuda":
        torch.cuda.synchronize()
    seconds = time.perf_counter() - t
    root = zarr.open_group(str(out), mode="r")
    return ({"couplings": summary["n"], "seconds": seconds, "nfe": summary["nfe"],
             "solves": summary["solves"]},
            root["noise"][:], root["action"][:], root["window"][:])


@torch.no_grad()
def run_reference(policy: Policy, data: PolicyData, windows: np.ndarray, noise: np.ndarray,
                  k: int, ref_batch: int, t0: float, rtol: float, atol: float
                  ) -> tuple[dict, np.ndarray]:
    """SeFA gen_data: per dataloader batch, per sample, one scipy RK45 on the flattened batch.

    noise: (len(windows) * K, T, Da), row w * K + j = window w, sample j (ours' layout).
    Returns the timing and the generated chunks in the same layout.
    """
    model = policy.model
    shape_tail = noise.shape[1:]
    out = np.empty_like(noise)
    nfe = solves = 0
    t = time.perf_counter()
    for b in range(0, len(windows), ref_batch):
        block = windows[b:b + ref_batch]
        nb = len(block)
        obs, _ = data.tensors(data.train, block, torch.device("cpu"))
        for j in range(k):
            cond = model.encode(obs)  # the reference encodes inside every sampling call
            rows = (b + np.arange(nb)) * k + j
            y0 = noise[rows].astype(np.float64).ravel()

            def fun(tt, y, cond=cond, nb=nb):
                x = torch.from_numpy(y.reshape(nb, *shape_tail)).float()
                v = model.velocity(x, torch.full((nb,), tt, dtype=torch.float32), cond)
                return v.double().numpy().ravel()

            sol = solve_ivp(fun, (t0, 1.0), y0, method="RK45", rtol=rtol, atol=atol)
            if not sol.success:
                raise RuntimeError(f"solve_ivp failed: {sol.message}")
            out[rows] = sol.y[:, -1].reshape(nb, *shape_tail).astype(np.float32)
            nfe += sol.nfev
            solves += 1
    seconds = time.perf_counter() - t
    return {"couplings": len(windows) * k, "seconds": seconds, "nfe": nfe, "solves": solves}, out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--workspace", type=Path, help="keep (and reuse) the store and trained policy here")
    ap.add_argument("--checkpoint", type=Path, help="a trained sefa policy (run or checkpoint dir)")
    ap.add_argument("--store", type=Path, help="the Zarr store it was trained on")
    ap.add_argument("--train-steps", type=int, default=400, help="steps of the default quick policy")
    ap.add_argument("--windows", type=int, default=128, help="N training windows (evenly spread)")
    ap.add_argument("--samples", type=int, default=10, help="K noises per window")
    ap.add_argument("--ref-batch", type=int, default=64, help="the reference's dataloader batch")
    ap.add_argument("--rtol", type=float, default=1e-5)
    ap.add_argument("--atol", type=float, default=1e-5)
    ap.add_argument("--repeat", type=int, default=3, help="runs per method (interleaved); the fastest is kept")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    if (args.checkpoint is None) != (args.store is None):
        ap.error("--checkpoint and --store go together")

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        load_before = os.getloadavg()[0]
        setup = time.perf_counter()
        if args.checkpoint is not None:
            ckpt, store = args.checkpoint, args.store
        else:
            work = args.workspace or tmp / "work"
            work.mkdir(parents=True, exist_ok=True)
            ckpt, store = build(work, args.train_steps)
        setup_s = time.perf_counter() - setup

        policy = Policy.load(ckpt, device="cpu")
        data = PolicyData(policy.cfg, EpisodeStore.open(store), policy.normalizer)
        n_train = len(data.train)
        windows = window_subset(n_train, args.windows)
        n, k = len(windows), args.samples
        t_eps = policy.cfg.flow.t_eps
        params = sum(p.numel() for p in policy.model.parameters())

        # warm-up (first-call allocations, lazy init) on a couple of windows, not timed
        run_ours(policy, store, tmp / "warm.zarr", 2, 2, 2, args.rtol, args.atol)

        # each method runs --repeat times, interleaved, and keeps its fastest run: the host may
        # be shared, and interleaving spreads any outside load over all methods alike
        labels = {"n": f"ours torch RK45, cpu, batch_windows={n} ({n * k} chunks/solve)",
                  "b": f"ours torch RK45, cpu, batch_windows={args.ref_batch} "
                       f"({min(n, args.ref_batch) * k} chunks/solve)",
                  "ref": f"reference scipy solve_ivp RK45 (float64, cpu), batch {args.ref_batch}, "
                         f"1 sample/solve ({min(n, args.ref_batch)} chunks/solve)"}
        best: dict[str, dict] = {}
        times: dict[str, list[float]] = {key: [] for key in labels}

        def keep(key: str, r: dict) -> None:
            times[key].append(r["seconds"])
            if key not in best or r["seconds"] < best[key]["seconds"]:
                best[key] = r

        noise = action = ref_action = None
        for rep in range(args.repeat):
            r, nz, act, wins = run_ours(policy, store, tmp / f"ours_n{rep}.zarr", args.windows, k, n,
                                        args.rtol, args.atol)
            if noise is None:
                assert np.array_equal(wins, np.repeat(windows, k))
                noise, action = nz, act
            keep("n", r)
            r, *_ = run_ours(policy, store, tmp / f"ours_b{rep}.zarr", args.windows, k, args.ref_batch,
                             args.rtol, args.atol)
            keep("b", r)
            r, ref_out = run_reference(policy, data, windows, noise, k, args.ref_batch, t_eps,
                                       args.rtol, args.atol)
            ref_action = ref_out if ref_action is None else ref_action
            keep("ref", r)
        if torch.cuda.is_available():
            gpu = Policy.load(ckpt, device="cuda")
            run_ours(gpu, store, tmp / "warm_gpu.zarr", 2, 2, 2, args.rtol, args.atol)
            for bw in (n, args.ref_batch):
                key = f"cuda{bw}"
                labels[key] = f"ours torch RK45, cuda, batch_windows={bw} ({min(n, bw) * k} chunks/solve)"
                times[key] = []
                for rep in range(args.repeat):
                    r, *_ = run_ours(gpu, store, tmp / f"gpu_{bw}_{rep}.zarr", args.windows, k, bw,
                                     args.rtol, args.atol)
                    keep(key, r)
        order = ["n", "b"] + [key for key in labels if key.startswith("cuda")] + ["ref"]
        rows = [{"method": labels[key], **best[key], "all_seconds": times[key]} for key in order]
        ref = best["ref"]
        load_after = os.getloadavg()[0]
        for r in rows:
            r["couplings_per_s"] = r["couplings"] / r["seconds"]
            r["speedup"] = ref["seconds"] / r["seconds"]

        diff = np.abs(action.astype(np.float64) - ref_action.astype(np.float64))
        agreement = {"mean_abs_diff": float(diff.mean()), "max_abs_diff": float(diff.max()),
                     "mean_abs_action": float(np.abs(ref_action).mean()),
                     "per_chunk_mean_abs_diff_p99": float(np.percentile(diff.mean(axis=(1, 2)), 99))}

    out = {"machine": {"platform": platform.platform(), "processor": platform.machine(),
                       "cpu_count": os.cpu_count(), "torch_threads": torch.get_num_threads(),
                       "torch": torch.__version__, "scipy": scipy.__version__,
                       "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
                       "loadavg_1min_start_end": [load_before, load_after]},
           "checkpoint": str(args.checkpoint) if args.checkpoint else f"quick MLP base policy, "
                                                                   f"{args.train_steps} steps",
           "params": params, "setup_s": setup_s, "train_windows": n_train, "windows": n,
           "samples_per_window": k, "ref_batch": args.ref_batch, "rtol": args.rtol,
           "atol": args.atol, "t0": t_eps, "repeat": args.repeat, "horizon": int(noise.shape[1]),
           "action_dim": int(noise.shape[2]), "rows": rows, "agreement": agreement}
    if args.json:
        print(json.dumps(out, indent=2))
        return
    m = out["machine"]
    print(f"reflow coupling generation, Push-T low-dim; {m['processor']}, {m['cpu_count']} CPUs, "
          f"{m['torch_threads']} torch threads, torch {m['torch']}, scipy {m['scipy']}, "
          f"device cpu{' + cuda ' + m['cuda'] if m['cuda'] else ' (no CUDA)'}")
    print(f"host 1-min load average {load_before:.2f} at start, {load_after:.2f} at end "
          f"(> 0 before we start = other processes sharing the {m['cpu_count']} CPUs)")
    print(f"policy: {out['checkpoint']} ({params / 1e6:.2f} M params); setup {setup_s:.0f} s")
    print(f"{n} of {n_train} training windows x K={k} samples = {n * k} couplings of "
          f"({out['horizon']}, {out['action_dim']}); RK45 rtol={args.rtol:g} atol={args.atol:g}, "
          f"t {t_eps:g} -> 1")
    print(f"best of {args.repeat} interleaved runs per method (all runs' seconds in --json)")
    print(f"{'method':88s} {'couplings':>9s} {'seconds':>8s} {'coupl/s':>9s} {'NFE':>7s} "
          f"{'solves':>6s} {'speedup':>8s}")
    for r in rows:
        print(f"{r['method']:88s} {r['couplings']:9d} {r['seconds']:8.2f} {r['couplings_per_s']:9.1f} "
              f"{r['nfe']:7d} {r['solves']:6d} {r['speedup']:7.1f}x")
    a = agreement
    print(f"agreement, ours (batch_windows={n}) vs reference from the same noise: mean |diff| "
          f"{a['mean_abs_diff']:.2e}, max {a['max_abs_diff']:.2e}, p99 per-chunk mean "
          f"{a['per_chunk_mean_abs_diff_p99']:.2e} (mean |action| {a['mean_abs_action']:.3f}, "
          f"normalized action space)")


if __name__ == "__main__":
    main()
