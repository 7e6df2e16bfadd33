"""Rectified flow, as small pure functions. Convention: see `sefa_model.config.FlowConfig`.

    x0 ~ N(0, I)              noise, t = 0
    x1                        the normalized action chunk, t = 1
    x_t = t x1 + (1 - t) x0
    v*  = x1 - x0             the regression target of the velocity network
"""

from __future__ import annotations

from typing import Callable

import torch
import torch.nn.functional as F

# velocity(x: (B, T, Da), t: (B,) in [0, 1]) -> (B, T, Da), the observation already bound in
Velocity = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


def interpolate(x0: torch.Tensor, x1: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """x_t for t of shape (B,), broadcast over the chunk."""
    t = t.view(-1, *([1] * (x1.dim() - 1)))
    return t * x1 + (1 - t) * x0


def sample_t(batch: int, t_eps: float, generator: torch.Generator | None = None,
             device: torch.device | str = "cpu") -> torch.Tensor:
    """t ~ U[t_eps, 1]: SeFA's reference code keeps t away from the pure-noise end."""
    u = torch.rand(batch, generator=generator, device="cpu")
    return (t_eps + (1 - t_eps) * u).to(device)


def euler_grid_t(batch: int, t_eps: float, steps: int,
                 generator: torch.Generator | None = None) -> torch.Tensor:
    """t drawn uniformly from the times `steps` Euler steps from t_eps visit:
    t_eps + i (1 - t_eps) / steps, i = 0 .. steps - 1 (a k-step student's training times)."""
    i = torch.randint(0, steps, (batch,), generator=generator, device="cpu")
    return t_eps + (1 - t_eps) * i.to(torch.float32) / steps


def flow_loss(velocity: Velocity, x0: torch.Tensor, x1: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Mean squared error between the predicted and the straight-line velocity. With t = 0 this
    is the one-step distillation loss: x0 + v(x0, 0) should land on x1."""
    return F.mse_loss(velocity(interpolate(x0, x1, t), t), x1 - x0)
