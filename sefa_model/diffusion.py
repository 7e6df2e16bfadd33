"""The diffusion baseline: an epsilon-prediction DDPM on the same network, with Diffusion Policy's
noise schedule and samplers taken from `diffusers` (the library Diffusion Policy itself uses),
so that the baseline is theirs and not our re-derivation of it.

    x1                                  the normalized action chunk
    noise ~ N(0, I),  k ~ U{0, ..., K-1}  (K = num_train_timesteps = 100)
    x_k = sqrt(abar_k) x1 + sqrt(1 - abar_k) noise
    loss = || eps_theta(x_k, k, obs) - noise ||^2

Sampling starts from pure noise and runs the scheduler's reverse steps (DDPM: all 100, with
fresh noise each step; DDIM: a deterministic subset), clipping the predicted x1 to [-1, 1] as
Diffusion Policy does; each step is one network evaluation.
"""

from __future__ import annotations

from typing import Callable

import torch
import torch.nn.functional as F

from sefa_model.config import DiffusionConfig
from sefa_model.solvers import SolveResult

# eps_theta(x: (B, T, Da), k: (B,) integer timesteps) -> (B, T, Da)
NoisePredictor = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]

SAMPLERS = ("ddpm", "ddim")


def make_scheduler(cfg: DiffusionConfig, sampler: str = "ddpm"):
    """Diffusion Policy's DDPMScheduler / DDIMScheduler settings (`fixed_small` variance, DDIM
    with `set_alpha_to_one` and no step offset)."""
    from diffusers import DDIMScheduler, DDPMScheduler  # imported here: slow to import

    common = dict(num_train_timesteps=cfg.num_train_timesteps, beta_start=cfg.beta_start,
                  beta_end=cfg.beta_end, beta_schedule=cfg.beta_schedule,
                  clip_sample=cfg.clip_sample, prediction_type="epsilon")
    if sampler == "ddpm":
        return DDPMScheduler(variance_type="fixed_small", **common)
    if sampler == "ddim":
        return DDIMScheduler(set_alpha_to_one=True, steps_offset=0, **common)
    raise ValueError(f"unknown diffusion sampler {sampler!r}; valid: {', '.join(SAMPLERS)}")


def sample_timesteps(batch: int, num_train_timesteps: int,
                     generator: torch.Generator | None = None) -> torch.Tensor:
    """k ~ U{0, ..., K-1}, one per sample (int64, CPU: drawn from the step's generator)."""
    return torch.randint(0, num_train_timesteps, (batch,), generator=generator)


def ddpm_loss(eps_model: NoisePredictor, noise: torch.Tensor, x1: torch.Tensor, k: torch.Tensor,
              scheduler) -> torch.Tensor:
    """Mean squared error of the predicted noise at the noised chunk x_k."""
    noisy = scheduler.add_noise(x1, noise, k)
    return F.mse_loss(eps_model(noisy, k), noise)


def denoise(eps_model: NoisePredictor, noise: torch.Tensor, cfg: DiffusionConfig, *,
            sampler: str = "ddpm", steps: int | None = None,
            generator: torch.Generator | None = None, scheduler=None) -> SolveResult:
    """Run the reverse process from `noise` (B, T, Da). `steps` defaults to the config's
    inference steps; DDPM's per-step noise comes from `generator` (on the noise's device)."""
    steps = steps or cfg.inference_steps
    if not 1 <= steps <= cfg.num_train_timesteps:
        raise ValueError(f"{sampler} steps must be in [1, {cfg.num_train_timesteps}], got {steps}")
    scheduler = scheduler or make_scheduler(cfg, sampler)
    scheduler.set_timesteps(steps)
    x = noise
    batch = x.shape[0]
    for k in scheduler.timesteps:
        eps = eps_model(x, torch.full((batch,), int(k), device=x.device, dtype=torch.long))
        x = scheduler.step(eps, k, x, generator=generator).prev_sample
    return SolveResult(x=x, nfe=len(scheduler.timesteps), steps=len(scheduler.timesteps))
