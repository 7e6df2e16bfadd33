"""Reflow couplings: for every training window, K noises pushed through the learned flow.

Each block of windows is solved as ONE batched ODE on the model's device: the observation is
encoded once per window, repeated K times, and the solver integrates all B*K chunks together:
"rk45" with one shared step size, as the reference's flattened scipy solve, or "rk45-ps" /
"dop853-ps" with a step size per chunk (see sefa_model.solvers).

The noise of window w in round r is drawn on the CPU from a generator seeded by (seed, r, w)
alone, and the blocks are fixed by the window list, not by the number of processes: under
torchrun rank i solves blocks i, i + N, ..., rank 0 gathers them, and the couplings are the
same as one process's. Each reflow round draws fresh noise. The couplings are written as a
Zarr group:

    noise   (M, T, Da) float32   x0, the starting noise
    action  (M, T, Da) float32   the generated chunk x1, in normalized action space
    window  (M,) int64           the training window (row of the train SequenceSampler)
    attrs: the provenance (sefa_model/couplings.py), samples_per_window, solver, rtol, atol, t0, nfe (calls, total), sample_evals (rows
           evaluated, total), solves, source checkpoint, and `expert_drift`: how far the
           generated chunks lie from the expert chunk of their own window (the alignment
           metric: mean, quantiles, and the fraction within each of DRIFT_EPS)
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from sefa_data.zarr_store import EpisodeStore
from sefa_model.alignment import chunk_distance
from sefa_model.couplings import write_couplings
from sefa_model.features import cached_window_features
from sefa_model.policy import Policy
from sefa_model.progress import report
from sefa_data.errors import SefaInputError
from sefa_model.distributed import DistContext, context
from sefa_model.policy_data import PolicyData
from sefa_model.solvers import ADAPTIVE
from sefa_model.train_batches import step_seed


DRIFT_EPS = (0.02, 0.05, 0.1, 0.2)


def expert_drift(generated: np.ndarray, expert: np.ndarray) -> dict:
    """Summary of the distances between generated chunks and their windows' expert chunks
    (both (M, T, Da), normalized): what selective alignment would replace at each eps."""
    d = chunk_distance(generated, expert).astype(np.float64)
    q = np.quantile(d, [0.1, 0.5, 0.9]) if len(d) else [float("nan")] * 3
    return {"mean": float(d.mean()) if len(d) else float("nan"),
            "q10": float(q[0]), "median": float(q[1]), "q90": float(q[2]),
            "within": {f"{e:g}": float((d < e).mean()) if len(d) else float("nan") for e in DRIFT_EPS}}


@dataclass
class CouplingConfig:
    samples_per_window: int = 10  # K, the reference's sample_per_cond
    solver: str = "rk45"  # any of sefa_model.solvers.METHODS; rk45 is the reference's
    rtol: float = 1e-5
    atol: float = 1e-5
    steps: int | None = None  # fixed-step solvers only
    batch_windows: int = 256  # windows per solve; each solve integrates batch_windows * K chunks
    max_windows: int | None = None  # a deterministic subset of the training windows (quick runs)
    seed: int = 0
    iteration: int = 1  # the reflow round: every round draws fresh noise


def window_noise(seed: int, iteration: int, windows: np.ndarray, k: int, shape: tuple[int, int]
                 ) -> torch.Tensor:
    """(len(windows) * k, *shape) standard normal noise, K rows per window, each window's rows
    drawn on the CPU from its own generator: independent of blocks, ranks and devices."""
    out = torch.empty(len(windows) * k, *shape)
    gen = torch.Generator()
    for i, w in enumerate(windows):
        gen.manual_seed(step_seed(seed, int(w), 7000 + iteration))
        out[i * k:(i + 1) * k] = torch.randn(k, *shape, generator=gen)
    return out


def window_subset(n: int, max_windows: int | None) -> np.ndarray:
    """Every window, or `max_windows` evenly spread ones (deterministic, covers all episodes)."""
    if max_windows is None or max_windows >= n:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, max_windows).round().astype(np.int64))


@torch.no_grad()
def generate_couplings(policy: Policy, store_path: Path, out: Path, cfg: CouplingConfig,
                       progress: Callable[[int, int], None] = lambda done, total: None,
                       ctx: DistContext | None = None, source: str | None = None,
                       features_cache: Path | None = None) -> dict:
    """Write the couplings of `policy` on the store's training windows to `out` (atomically).
    Under torchrun every rank calls this with its own policy copy; rank 0 writes. `source`
    names the checkpoint in the attributes when `policy.path` is a temporary one. With
    `features_cache`, every window's condition is read from (or computed once into) that cache
    instead of encoding each block (sefa_model/features.py)."""
    ctx = ctx or context()
    if policy.cfg.objective != "flow":
        raise SefaInputError(f"reflow needs a rectified-flow policy; this checkpoint is the "
                             f"{policy.cfg.objective} baseline", file=policy.path)
    data = PolicyData(policy.cfg, EpisodeStore.open(store_path), policy.normalizer)
    windows = window_subset(len(data.train), cfg.max_windows)
    k = cfg.samples_per_window
    shape = (policy.cfg.policy.horizon, policy.cfg.shape_meta.action.shape[-1])
    blocks = list(range(0, len(windows), cfg.batch_windows))
    mine = ctx.shard(blocks)
    started = time.perf_counter()
    features = None
    if features_cache is not None:
        features = cached_window_features(policy.model, data, windows, policy.device,
                                          features_cache, is_main=ctx.is_main, barrier=ctx.barrier)
    solved = []  # (block start, noise, action, nfe)
    if ctx.is_main:  # the bar from the first second, its clock including the first block
        report("couplings", 0, len(windows), couplings=0)
    for n, b in enumerate(mine):
        block = windows[b:b + cfg.batch_windows]
        if features is not None:
            cond = features[b:b + cfg.batch_windows].to(policy.device)
        else:
            obs, _ = data.tensors(data.train, block, policy.device)
            cond = policy.model.encode(obs)
        cond = cond.repeat_interleave(k, dim=0)  # (B*K, D)
        x0 = window_noise(cfg.seed, cfg.iteration, block, k, shape)
        result = policy.model.sample(cond, x0.to(policy.device, non_blocking=True), solver=cfg.solver,
                                     steps=None if cfg.solver in ADAPTIVE else cfg.steps,
                                     rtol=cfg.rtol, atol=cfg.atol)
        solved.append((b, x0.numpy(), result.x.float().cpu().numpy(), result.nfe, result.sample_evals))
        # rank 0 reports the whole job's progress, assuming the other ranks keep pace
        done = min(len(windows), (n + 1) * cfg.batch_windows * ctx.world)
        progress(done, len(windows))
        if ctx.is_main:
            report("couplings", done, len(windows), couplings=done * k,
                   NFE_per_solve=sum(s[3] for s in solved) / len(solved))
    parts = ctx.gather(solved)
    summary = None
    if ctx.is_main:
        solved = sorted((p for part in parts for p in part), key=lambda p: p[0])
        expert = data.expert_chunks(windows)
        drift = expert_drift(np.concatenate([s[2] for s in solved]), np.repeat(expert, k, axis=0))
        summary = _write(out, windows, k, solved, started, {
            "expert_drift": drift,
            "samples_per_window": k, "solver": cfg.solver, "rtol": cfg.rtol, "atol": cfg.atol,
            "steps": cfg.steps, "t0": policy.cfg.flow.time_span[0], "seed": cfg.seed,
            "iteration": cfg.iteration, "processes": ctx.world, "device": str(policy.device),
            "source_checkpoint": source or policy.path, "space": "normalized action",
            **data.provenance()})
    summary = ctx.broadcast(summary)
    return summary


def _write(out: Path, windows: np.ndarray, k: int, solved: list, started: float,
           attrs: dict) -> dict:
    noise = np.concatenate([s[1] for s in solved])
    action = np.concatenate([s[2] for s in solved])
    nfe = sum(s[3] for s in solved)
    sample_evals = sum(s[4] for s in solved)
    m = len(noise)
    seconds = time.perf_counter() - started
    summary = {"n": m, "windows": int(len(windows)), **attrs, "nfe": nfe,
               "solves": len(solved), "nfe_per_solve": nfe / max(1, len(solved)),
               "sample_evals": sample_evals, "evals_per_coupling": sample_evals / max(1, m),
               "seconds": seconds, "couplings_per_s": m / seconds}
    write_couplings(out, noise, action, np.repeat(windows, k), summary)
    return summary
