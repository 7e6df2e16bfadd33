"""The diffusion baseline (`sefa train --objective ddpm`): Diffusion Policy's epsilon
prediction on expert chunks, sampled by its reverse process (DDPM, or DDIM with fewer steps)."""

from __future__ import annotations

from sefa_model.diffusion import ddpm_loss, make_scheduler, sample_timesteps
from sefa_model.methods.base import Method, StepCalls, Times


class Diffusion(Method):
    name = "ddpm"
    label = "diffusion"
    summary = "the diffusion baseline: epsilon prediction, DDPM or DDIM sampling"
    pairs = "expert"
    student = False

    def draw(self, cfg, n, gen):
        return Times(sample_timesteps(n, cfg.diffusion.num_train_timesteps, gen))

    def loss(self, cfg, calls: StepCalls, x0, x1, times, gen=None):
        scheduler = make_scheduler(cfg.diffusion)
        return ddpm_loss(lambda x, k: calls.f(x, k), x0, x1, times.t, scheduler)

    def check(self, flow):
        pass  # sampled by its reverse process, not by the flow's solver

    def time_words(self, flow):
        return "diffusion timesteps"


METHOD = Diffusion()
