"""The diffusion baseline (`sefa train --objective ddpm`): an epsilon-prediction DDPM on the same
network, with Diffusion Policy's noise schedule and samplers taken from `diffusers` (the library
Diffusion Policy itself uses), so that the baseline is theirs and not our re-derivation of it.

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
from sefa_model.flow.solvers import SolveResult
from sefa_model.methods.base import Method, StepCalls, Times

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
    inference steps. DDPM's per-step noise is drawn by `generator` on its own device, all
    steps in one draw and one copy (a CPU generator gives the same noise on every device)."""
    from sefa_model.distributed import cpu_noise

    steps = steps or cfg.inference_steps
    if not 1 <= steps <= cfg.num_train_timesteps:
        raise ValueError(f"{sampler} steps must be in [1, {cfg.num_train_timesteps}], got {steps}")
    scheduler = scheduler or make_scheduler(cfg, sampler)
    scheduler.set_timesteps(steps)
    x = noise
    batch = x.shape[0]
    timesteps = [int(k) for k in scheduler.timesteps]
    step_noise = (cpu_noise((len(timesteps), *x.shape), generator, x.device).to(x.dtype)
                  if sampler == "ddpm" else None)
    for i, k in enumerate(timesteps):
        eps = eps_model(x, torch.full((batch,), k, device=x.device, dtype=torch.long))
        if sampler == "ddpm":
            x = ddpm_step(scheduler, eps, k, x, step_noise[i])
        else:
            x = scheduler.step(eps, k, x).prev_sample
    return SolveResult(x=x, nfe=len(timesteps), steps=len(timesteps))


def ddpm_step(scheduler, eps: torch.Tensor, k: int, x: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
    """x_{k-1} from x_k: diffusers' DDPMScheduler.step (epsilon prediction, clipped x1,
    `fixed_small` variance) with the step's noise given rather than drawn inside, so that a
    whole trajectory's noise is drawn once. Tested equal to `scheduler.step`."""
    prev = scheduler.previous_timestep(k)
    abar = scheduler.alphas_cumprod[k]
    abar_prev = scheduler.alphas_cumprod[prev] if prev >= 0 else scheduler.one
    beta = 1 - abar / abar_prev
    x1 = (x - (1 - abar) ** 0.5 * eps) / abar ** 0.5
    if scheduler.config.clip_sample:
        x1 = x1.clamp(-scheduler.config.clip_sample_range, scheduler.config.clip_sample_range)
    mean = ((abar_prev ** 0.5 * beta / (1 - abar)) * x1
            + ((1 - beta) ** 0.5 * (1 - abar_prev) / (1 - abar)) * x)
    if k == 0:
        return mean
    return mean + scheduler._get_variance(k) ** 0.5 * noise

class Diffusion(Method):
    name = "ddpm"
    label = "diffusion"
    summary = "the diffusion baseline: epsilon prediction, DDPM or DDIM sampling"
    pairs = "expert"
    student = False
    solves_ode = False  # a reverse process: no couplings, no unrolled export
    yardstick = "ddpm"

    def draw(self, cfg, n, gen):
        return Times(sample_timesteps(n, cfg.diffusion.num_train_timesteps, gen))

    def loss(self, cfg, calls: StepCalls, x0, x1, times, gen=None):
        scheduler = make_scheduler(cfg.diffusion)
        return ddpm_loss(lambda x, k: calls.f(x, k), x0, x1, times.t, scheduler)

    def kind(self):
        return "ddpm"

    def network(self, model, x, t, cond, d=None):
        return model.predict_noise(x, t, cond)  # t: the integer timestep k

    def probe_time(self, cfg, device):
        return torch.full((1,), cfg.diffusion.num_train_timesteps // 2, device=device,
                          dtype=torch.long)

    def solvers(self):
        return SAMPLERS

    def default_solver(self, cfg):
        return cfg.diffusion.sampler, cfg.diffusion.inference_steps

    def fallback_steps(self, cfg):
        return cfg.diffusion.inference_steps

    def family(self, cfg):
        return "ddpm"

    def sample(self, model, cond, noise, solver, steps, *, generator=None, rtol=None, atol=None,
               graphs=None):
        return denoise(lambda x, k: model.predict_noise(x, k, cond), noise, model.cfg.diffusion,
                       sampler=solver, steps=steps, generator=generator)

    def solve_progress(self, cfg, calls, t_in):
        return calls, cfg.diffusion.inference_steps  # one network call per reverse step

    def check(self, flow):
        pass  # sampled by its reverse process, not by the flow's solver

    def time_words(self, flow):
        return "diffusion timesteps"

    def convention(self, cfg):
        d = cfg.diffusion
        return {"diffusion_convention": {
            "prediction": "epsilon", "x_k": "sqrt(abar_k) x1 + sqrt(1 - abar_k) noise",
            "k_train": f"U{{0..{d.num_train_timesteps - 1}}}", "schedule": d.beta_schedule,
            "clip_sample": d.clip_sample}}


METHOD = Diffusion()
