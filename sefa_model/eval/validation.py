"""The sampled validation: the one definition of a policy's validation action MSE, used by
training's validation (every `training.val_every` steps) and by `sefa eval --offline`, so that
one checkpoint gives one number in both.

- windows (`sampled_windows`): `count` windows evenly spread over the validation windows (all of
  them when there are fewer). Training samples `training.val_sample_windows` of them; `sefa eval
  --offline` the same by default.
- noise: a CPU generator seeded with `seed` (the run's `training.seed`) draws one chunk per
  (sample, window), sample-major, so sample 0 of each window gets the same noise whatever the
  number of samples (training draws 1, the offline evaluation K for its spread). The flow's
  solvers are deterministic from there; a diffusion sampler draws more noise at every step, so
  its sample 0 is the same only for the same number of samples.
- action MSE (`action_errors`): sample 0 against the expert chunk, in action units, averaged
  over the windows, the horizon and the action dimensions; beside it, on the same windows, the
  MSE of always predicting the training set's mean action (the baseline to beat).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from sefa_model.distributed import cpu_noise
from sefa_model.data.windows import PolicyData


@dataclass
class SampledChunks:
    windows: np.ndarray  # (W,) indices into the sampler
    obs: dict[str, torch.Tensor]  # the windows' model inputs
    sampled: torch.Tensor  # (W, K, T, Da) normalized
    truth: torch.Tensor  # (W, T, Da) normalized expert chunks
    nfe: int


def sampled_windows(n: int, count: int) -> np.ndarray:
    """`count` of n windows, evenly spread, first and last included (all n when count >= n)."""
    return np.unique(np.linspace(0, n - 1, min(n, count)).round().astype(np.int64))


@torch.no_grad()
def sample_windows(model, data: PolicyData, sampler, count: int, samples: int, seed: int,
                   device: torch.device, solver: str | None = None, steps: int | None = None
                   ) -> SampledChunks:
    """`samples` chunks for each of `count` windows of `sampler` (see the module's rules)."""
    idx = sampled_windows(len(sampler), count)
    obs, x1 = data.tensors(sampler, idx, device)
    # sample-major rows: rows [k W, (k + 1) W) are sample k of every window
    cond = model.encode({k: v.repeat(samples, *([1] * (v.ndim - 1))) for k, v in obs.items()})
    gen = torch.Generator().manual_seed(seed)
    noise = cpu_noise((samples * len(idx), *x1.shape[1:]), gen, device)
    result = model.sample(cond, noise, solver=solver, steps=steps, generator=gen)
    sampled = result.x.reshape(samples, len(idx), *x1.shape[1:]).transpose(0, 1)
    return SampledChunks(idx, obs, sampled, x1, result.nfe)


def action_errors(chunks: SampledChunks, data: PolicyData) -> dict[str, float]:
    """{"action_mse", "mean_action_mse"}: sample 0's MSE and the mean action's, in action
    units, on the same windows."""
    action = data.processor.action
    truth = action.unnormalize(chunks.truth).cpu().numpy().astype(np.float64)
    pred = action.unnormalize(chunks.sampled[:, 0]).cpu().numpy().astype(np.float64)
    return {"action_mse": float(np.mean((pred - truth) ** 2)),
            "mean_action_mse": float(np.mean((data.mean_action - truth) ** 2))}
