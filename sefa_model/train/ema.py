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
        """`step` is the number of optimizer steps taken so far, this one included.

        Over the whole parameter list at once (torch._foreach_*): on a GPU a few kernel
        launches per step instead of two per tensor; on the CPU the same per-tensor ops, so the
        same numbers (tests/sefa_model_tests/test_device_batches.py)."""
        decay = ema_decay(step - 1, self.power, self.inv_gamma, self.max_decay)
        trained, frozen = ([], []), ([], [])
        for ema_p, p in zip(self.model.parameters(), model.parameters()):
            pair = trained if p.requires_grad else frozen
            pair[0].append(ema_p)
            pair[1].append(p.detach())
        if trained[0]:
            torch._foreach_mul_(trained[0], decay)
            torch._foreach_add_(trained[0], trained[1], alpha=1 - decay)
        # frozen: averaging equal values would still round them away from the original
        buffers = list(zip(self.model.buffers(), model.buffers()))
        copies = (frozen[0] + [e for e, _ in buffers], frozen[1] + [b for _, b in buffers])
        if copies[0]:
            torch._foreach_copy_(*copies)
