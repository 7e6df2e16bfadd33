"""Exponential moving average of weights, with Diffusion Policy's warm-up schedule.

decay(step) = 1 - (1 + step / inv_gamma) ** -power, clipped to [0, max_decay]: early steps follow
the raw weights closely, later ones average over ever longer windows.
"""

from __future__ import annotations

import copy

import torch
from torch import nn


def ema_decay(step: int, power: float = 0.75, inv_gamma: float = 1.0, max_decay: float = 0.9999) -> float:
    if step <= 0:
        return 0.0
    return float(min(max_decay, max(0.0, 1 - (1 + step / inv_gamma) ** -power)))


class EMA:
    def __init__(self, model: nn.Module, power: float = 0.75, inv_gamma: float = 1.0,
                 max_decay: float = 0.9999):
        self.model = copy.deepcopy(model).eval().requires_grad_(False)
        self.power, self.inv_gamma, self.max_decay = power, inv_gamma, max_decay

    @torch.no_grad()
    def update(self, model: nn.Module, step: int) -> None:
        """`step` is the number of optimizer steps taken so far, this one included."""
        decay = ema_decay(step - 1, self.power, self.inv_gamma, self.max_decay)
        for ema_p, p in zip(self.model.parameters(), model.parameters()):
            if p.requires_grad:
                ema_p.mul_(decay).add_(p.detach(), alpha=1 - decay)
            else:  # frozen: averaging equal values would still round them away from the original
                ema_p.copy_(p)
        for ema_b, b in zip(self.model.buffers(), model.buffers()):
            ema_b.copy_(b)
