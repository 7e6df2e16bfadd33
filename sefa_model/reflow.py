"""Reflow couplings: for every training window, K noises pushed through the learned flow.

Each block of windows is solved as ONE batched ODE on the model's device: the observation is
encoded once per window, repeated K times, and the solver integrates all B*K chunks together:
"rk45" with one shared step size, as the reference's flattened scipy solve, or "rk45-ps" /
"dop853-ps" with a step size per chunk, which makes a chunk's result independent of the other
chunks of its block (see sefa_model.solvers). The couplings are written as a Zarr group:

    noise   (M, T, Da) float32   x0, the starting noise
    action  (M, T, Da) float32   the generated chunk x1, in normalized action space
    window  (M,) int64           the training window (row of the train SequenceSampler)
    attrs: samples_per_window, solver, rtol, atol, t0, nfe (calls, total), sample_evals (rows
           evaluated, total), solves, source checkpoint
"""

from __future__ import annotations

import os
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch
import zarr

from sefa_data.zarr_store import EpisodeStore
from sefa_model.policy import Policy
from sefa_data.errors import SefaInputError
from sefa_model.solvers import ADAPTIVE, solve
from sefa_model.training import PolicyData, step_generator


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


def window_subset(n: int, max_windows: int | None) -> np.ndarray:
    """Every window, or `max_windows` evenly spread ones (deterministic, covers all episodes)."""
    if max_windows is None or max_windows >= n:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, max_windows).round().astype(np.int64))


@torch.no_grad()
def generate_couplings(policy: Policy, store_path: Path, out: Path, cfg: CouplingConfig,
                       progress: Callable[[int, int], None] = lambda done, total: None) -> dict:
    """Write the couplings of `policy` on the store's training windows to `out` (atomically)."""
    if policy.cfg.objective != "flow":
        raise SefaInputError(f"reflow needs a rectified-flow policy; this checkpoint is the "
                             f"{policy.cfg.objective} baseline", file=policy.path)
    data = PolicyData(policy.cfg, EpisodeStore.open(store_path), policy.normalizer)
    windows = window_subset(len(data.train), cfg.max_windows)
    k = cfg.samples_per_window
    horizon = policy.cfg.policy.horizon
    action_dim = policy.cfg.shape_meta.action.shape[-1]
    t0 = policy.cfg.flow.t_eps
    tmp = out.with_name(f".{out.name}.tmp-{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        root = zarr.open_group(str(tmp), mode="w", zarr_format=2)
        m = len(windows) * k
        chunk = (max(1, 65536 // (horizon * action_dim)), horizon, action_dim)
        noise_arr = root.create_array("noise", shape=(m, horizon, action_dim), dtype="f4", chunks=chunk)
        action_arr = root.create_array("action", shape=(m, horizon, action_dim), dtype="f4", chunks=chunk)
        window_arr = root.create_array("window", shape=(m,), dtype="i8", chunks=(chunk[0] * 16,))
        nfe, sample_evals, solves, started = 0, 0, 0, time.perf_counter()
        noise_parts, action_parts = [], []
        for b in range(0, len(windows), cfg.batch_windows):
            block = windows[b:b + cfg.batch_windows]
            obs, _ = data.tensors(data.train, block, policy.device)
            cond = policy.model.encode(obs).repeat_interleave(k, dim=0)  # (B*K, D)
            gen = step_generator(cfg.seed, b // cfg.batch_windows, 7)
            x0 = torch.randn(len(block) * k, horizon, action_dim, generator=gen)
            result = solve(policy.model.velocity, x0.to(policy.device), cfg.solver, t0=t0, t1=1.0,
                           steps=None if cfg.solver in ADAPTIVE else cfg.steps,
                           rtol=cfg.rtol, atol=cfg.atol, cond=cond)
            noise_parts.append(x0.numpy())
            action_parts.append(result.x.float().cpu().numpy())
            nfe += result.nfe
            sample_evals += result.sample_evals
            solves += 1
            progress(min(b + cfg.batch_windows, len(windows)), len(windows))
        noise_arr[:] = np.concatenate(noise_parts)
        action_arr[:] = np.concatenate(action_parts)
        window_arr[:] = np.repeat(windows, k)
        seconds = time.perf_counter() - started
        summary = {"n": m, "windows": int(len(windows)), "samples_per_window": k,
                   "solver": cfg.solver, "rtol": cfg.rtol, "atol": cfg.atol, "steps": cfg.steps,
                   "t0": t0, "nfe": nfe, "solves": solves, "nfe_per_solve": nfe / max(1, solves),
                   "sample_evals": sample_evals, "evals_per_coupling": sample_evals / max(1, m),
                   "seconds": seconds, "couplings_per_s": m / seconds,
                   "source_checkpoint": policy.path, "space": "normalized action"}
        root.update_attributes(summary)
        if out.exists():
            shutil.rmtree(out)
        out.parent.mkdir(parents=True, exist_ok=True)
        os.replace(tmp, out)
        return summary
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
