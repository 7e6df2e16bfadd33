"""Offline evaluation of any checkpoint on the store's validation windows (no simulator).

- action MSE: sampled chunk vs the expert chunk, in action units, over the whole horizon;
- multimodality: for each observation, K sampled chunks; their spread (mean over the horizon and
  action dimensions of the per-element standard deviation across the K samples, in normalized
  action units) is compared with the expert spread, the same statistic over the expert chunks of
  the K training windows whose normalized observations are nearest. A one-step policy that
  collapsed onto the mean has a ratio near 0; one that keeps the demonstrations' variety is
  near 1.
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import torch

from sefa_data.errors import NonFiniteError
from sefa_data.zarr_store import EpisodeStore
from sefa_model.distributed import cpu_noise
from sefa_model.policy import Policy
from sefa_model.progress import report
from sefa_model.policy_data import PolicyData


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


@contextmanager
def _sampling_progress(policy: Policy, rows: int):
    """Report the batched solve's progress from the network calls it makes: a flow's time t
    (in thousandths of [t_eps, 1]), a diffusion sampler's step count."""
    calls = [0]
    total = policy.cfg.diffusion.inference_steps if policy.cfg.objective == "ddpm" else 1000

    def hook(module, args, output) -> None:
        calls[0] += 1
        if policy.cfg.objective == "ddpm":
            done = calls[0]
        else:  # the head sees t * time_scale; the furthest row tells how far the solve is
            done = int(round(1000 * float(args[1].max()) / policy.cfg.flow.time_scale))
        report("offline eval", min(done, total), total, NFE=calls[0], chunks=rows)

    handle = policy.model.head.register_forward_hook(hook)
    try:
        yield
    finally:
        handle.remove()
    # the hook sees where each call starts: a one-step policy's only call starts at t = 0, and
    # a solve that is over is at its end whatever the last call saw
    report("offline eval", total, total, NFE=calls[0], chunks=rows)


@torch.no_grad()
def evaluate_offline(checkpoint: str | Path, store_path: Path, *, windows: int = 256,
                     samples: int = 8, solver: str | None = None, steps: int | None = None,
                     seed: int = 0, device: str = "auto", log=lambda line: None) -> dict:
    policy = Policy.load(checkpoint, device=device)
    data = PolicyData(policy.cfg, EpisodeStore.open(store_path), policy.normalizer)
    if data.split_note:
        log(data.split_note)
    elif data.valid is None:
        log("warning: no validation windows (the store is shorter than a horizon): the "
            "training windows are evaluated, which flatters the policy")
    sampler = data.valid or data.train
    idx = np.unique(np.linspace(0, len(sampler) - 1, min(windows, len(sampler))).round().astype(int))
    obs, x1 = data.tensors(sampler, idx, policy.device)
    action = policy.processor.action
    truth = action.unnormalize(x1).cpu().numpy()

    gen = torch.Generator().manual_seed(seed)
    rep = {k: v.repeat_interleave(samples, 0) for k, v in obs.items()}
    cond = policy.model.encode(rep)  # already normalized inputs: the model directly, not predict_action
    shape = (len(idx) * samples, policy.cfg.policy.horizon, x1.shape[-1])
    from sefa_model.sampling import resolve_solver

    solver, steps = resolve_solver(policy.cfg, solver, steps)
    started = time.perf_counter()
    # noise (and DDPM's per-step noise) from the CPU generator: the same on every device
    with _sampling_progress(policy, len(idx) * samples):
        result = policy.model.sample(cond, cpu_noise(shape, gen, policy.device), solver=solver,
                                     steps=steps, generator=gen)
    seconds = time.perf_counter() - started
    bad = int((~torch.isfinite(result.x)).flatten(1).any(1).sum())
    if bad:  # a metric of NaN would be cached and compared as if it were a result
        raise NonFiniteError(f"the policy's actions are NaN or Inf for {bad} of {len(result.x)} "
                             f"sampled chunks ({solver}); no evaluation is recorded",
                             file=policy.path)
    sampled_n = result.x.cpu().numpy().reshape(len(idx), samples, *shape[1:])
    sampled = action.unnormalize(result.x).cpu().numpy().reshape(sampled_n.shape)

    # expert spread: chunks of the `samples` training windows with the nearest observations
    all_train = np.arange(len(data.train))
    train_obs, train_x1 = data.tensors(data.train, all_train, policy.device)
    near = nearest_windows(_flat_obs(policy, obs), _flat_obs(policy, train_obs), samples)
    expert_groups = train_x1.cpu().numpy()[near]
    model_spread = chunk_spread(sampled_n)
    expert_spread = chunk_spread(expert_groups)
    return {
        "checkpoint": policy.path, "kind": policy.kind, "solver": solver, "steps": steps,
        "nfe": result.nfe, "windows": int(len(idx)), "samples": samples,
        "split": ("valid" if data.split_note is None else "valid (window-level)")
                 if data.valid is not None else "train",
        "action_mse": float(np.mean((sampled[:, 0] - truth) ** 2)),
        "action_mse_best_of_k": float(np.mean(np.min(((sampled - truth[:, None]) ** 2).mean(axis=(2, 3)), axis=1))),
        "spread": float(model_spread.mean()), "expert_spread": float(expert_spread.mean()),
        "spread_ratio": float(model_spread.mean() / max(expert_spread.mean(), 1e-12)),
        "sampling_s": seconds, "device": str(policy.device),
    }
