"""Offline evaluation of any checkpoint on the store's validation windows (no simulator).

- action MSE: sampled chunk vs the expert chunk, in action units, over the whole horizon, and
  beside it the MSE of always predicting the training set's mean action on the same windows.
  Both are training's validation numbers (sefa_model/eval/validation.py: the same windows, noise
  and seed), so by default `sefa eval --offline` repeats what training reported;
- best-of-K MSE: the closest of the K samples per window;
- multimodality: for each observation, K sampled chunks; their spread (mean over the horizon and
  action dimensions of the per-element standard deviation across the K samples, in normalized
  action units) is compared with the expert spread, the same statistic over the expert chunks of
  the K training windows whose normalized observations are nearest. A one-step policy that
  collapsed onto the mean has a ratio near 0; one that keeps the demonstrations' variety is
  near 1. Where the expert spread is below `SPREAD_FLOOR` (the nearest windows' chunks are all
  but identical, e.g. an arm holding still) no ratio is given: it would only be a large number.
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import torch

from sefa_data.errors import NonFiniteError
from sefa_data.store.zarr_store import EpisodeStore
from sefa_model.policy.artifact import Policy
from sefa_model.policy.sampling import watching_solves
from sefa_model.progress import report
from sefa_model.data.windows import PolicyData
from sefa_model.eval.validation import action_errors, sample_windows, sampled_windows

# An expert spread below this (normalized action units, where the training actions span about
# [-1, 1]) makes spread / expert spread meaningless.
SPREAD_FLOOR = 1e-3


def spread_ratio(spread: float, expert_spread: float) -> tuple[float | None, str | None]:
    """(spread / expert spread, None), or (None, why not) when the expert spread is too small."""
    if expert_spread < SPREAD_FLOOR:
        return None, (f"expert spread {expert_spread:.2g} is below {SPREAD_FLOOR:g}: the nearest "
                      f"training windows' chunks are all but identical, so a ratio is meaningless")
    return spread / expert_spread, None


def chunk_spread(chunks: np.ndarray) -> np.ndarray:
    """(N, K, T, Da) -> (N,): mean per-element std across the K chunks of each group."""
    return chunks.std(axis=1).mean(axis=(1, 2))


def nearest_windows(query: np.ndarray, pool: np.ndarray, k: int, block: int = 256) -> np.ndarray:
    """(Q, D), (P, D) -> (Q, k) indices of the k nearest pool rows (Euclidean), blockwise."""
    out = []
    pool_sq = (pool ** 2).sum(1)
    for b in range(0, len(query), block):
        q = query[b:b + block]
        d = (q ** 2).sum(1)[:, None] - 2 * q @ pool.T + pool_sq[None]
        out.append(np.argpartition(d, kth=min(k, len(pool)) - 1, axis=1)[:, :k])
    return np.concatenate(out)


def _flat_obs(policy: Policy, obs: dict[str, torch.Tensor]) -> np.ndarray:
    parts = [v.reshape(v.shape[0], -1) for k, v in obs.items()
             if policy.cfg.shape_meta.obs[k].type == "low_dim"]
    return torch.cat(parts, 1).cpu().numpy() if parts else np.zeros((next(iter(obs.values())).shape[0], 0))


def lowdim_obs(data: PolicyData) -> dict[str, torch.Tensor]:
    """Every training window's low-dim observations as the policy sees them (normalized, its
    dims), with no image read: the neighbours of the expert spread are found by these alone,
    and reading every window's frames took half a minute after the bar on a camera store."""
    frames = data.train.frame_indices(np.arange(len(data.train)))[:, :data.cfg.policy.n_obs_steps]
    return {k: data.processor.obs.one(k, torch.from_numpy(
                np.ascontiguousarray(data.train.buffer(k)[frames])).float())
            for k, spec in data.cfg.shape_meta.obs.items() if spec.type == "low_dim"}


@contextmanager
def _sampling_progress(policy: Policy, rows: int):
    """Report the batched solve's progress from the network calls it makes: a flow's time t
    (in thousandths of [t_eps, 1]), a diffusion sampler's step count."""
    calls = [0]

    def on_call(n: int, done: int, total: int) -> None:
        calls[0] = n
        report("offline eval", done, total, NFE=n, chunks=rows)

    with watching_solves(policy.model, on_call):
        yield
    # the hook sees where each call starts: a one-step policy's only call starts at t = 0, and
    # a solve that is over is at its end whatever the last call saw
    total = policy.model.method.solve_progress(policy.cfg, 0, torch.zeros(1))[1]
    report("offline eval", total, total, NFE=calls[0], chunks=rows)


@torch.no_grad()
def evaluate_offline(checkpoint: str | Path, store_path: Path, *, windows: int | None = None,
                     samples: int = 8, solver: str | None = None, steps: int | None = None,
                     seed: int | None = None, device: str = "auto", log=lambda line: None) -> dict:
    """windows, seed: default the checkpoint's training.val_sample_windows and training.seed,
    so that action_mse is its training's validation action MSE."""
    policy = Policy.load(checkpoint, device=device)
    t_cfg = policy.cfg.training
    windows = windows if windows is not None else (t_cfg.val_sample_windows or 256)
    seed = t_cfg.seed if seed is None else seed
    data = PolicyData(policy.cfg, EpisodeStore.open(store_path), policy.normalizer)
    if data.split_note:
        log(data.split_note)
    elif data.valid is None:
        log("warning: no validation windows (the store is shorter than a horizon): the "
            "training windows are evaluated, which flatters the policy")
    sampler = data.valid or data.train
    from sefa_model.policy.sampling import resolve_solver

    solver, steps = resolve_solver(policy.cfg, solver, steps)
    n_windows = len(sampled_windows(len(sampler), windows))
    started = time.perf_counter()
    with _sampling_progress(policy, n_windows * samples):
        chunks = sample_windows(policy.model, data, sampler, windows, samples, seed,
                                policy.device, solver, steps)
    seconds = time.perf_counter() - started
    x = chunks.sampled
    bad = int((~torch.isfinite(x)).flatten(2).any(2).sum())
    if bad:  # a metric of NaN would be cached and compared as if it were a result
        raise NonFiniteError(f"the policy's actions are NaN or Inf for {bad} of "
                             f"{x.shape[0] * x.shape[1]} sampled chunks ({solver}); no "
                             f"evaluation is recorded", file=policy.path)
    sampled_n = x.cpu().numpy()
    sampled = policy.processor.action.unnormalize(x).cpu().numpy()
    truth = policy.processor.action.unnormalize(chunks.truth).cpu().numpy()

    # expert spread: chunks of the `samples` training windows with the nearest observations
    all_train = np.arange(len(data.train))
    report("offline eval: the expert spread", 0, 1, windows=len(all_train))
    near = nearest_windows(_flat_obs(policy, chunks.obs), _flat_obs(policy, lowdim_obs(data)),
                           samples)
    expert_groups = data.expert_chunks(all_train)[near]
    report("offline eval: the expert spread", 1, 1, windows=len(all_train))
    model_spread = float(chunk_spread(sampled_n).mean())
    expert_spread = float(chunk_spread(expert_groups).mean())
    ratio, ratio_note = spread_ratio(model_spread, expert_spread)
    return {
        "checkpoint": policy.path, "kind": policy.kind, "solver": solver, "steps": steps,
        "nfe": chunks.nfe, "windows": int(len(chunks.windows)), "samples": samples, "seed": seed,
        "split": ("valid" if data.split_note is None else "valid (window-level)")
                 if data.valid is not None else "train",
        **action_errors(chunks, data),
        "action_mse_best_of_k": float(np.mean(np.min(((sampled - truth[:, None]) ** 2).mean(axis=(2, 3)), axis=1))),
        "spread": model_spread, "expert_spread": expert_spread,
        "spread_ratio": ratio, "spread_note": ratio_note,
        "sampling_s": seconds, "device": str(policy.device),
    }
