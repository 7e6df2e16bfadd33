"""The 2-rectified-flow++ student (Lee, Lin, Fanti, NeurIPS 2024; code: sangyun884/rfpp), on the
stored couplings: trained over all t with a U-shaped t distribution (most weight near both
ends, where a one-step sampler's error starts and lands), a pseudo-Huber loss (robust to the
few couplings far from the rest), initialised from the teacher, and sampled with one Euler step
from t = 0. LPIPS, the paper's image term, has no meaning for an action chunk and is left out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from sefa_data.ranges import POSITIVE, knob
from sefa_model.flow.rectified_flow import interpolate
from sefa_model.methods.base import Method, StepCalls, Times


@dataclass
class RFPPKnobs:
    """2-RF++'s settings (`method_config.u_shape_a=...` in the student's train overrides)."""

    # rfpp's t_dist: density proportional to cosh(a (t - 1/2)), a = 4
    u_shape_a: float = knob(4.0, POSITIVE)
    # iCT's and rfpp's constant: the pseudo-Huber c = huber_c sqrt(data dimension)
    huber_c: float = knob(0.00054, POSITIVE)


def u_shaped_t(n: int, a: float, gen: torch.Generator) -> torch.Tensor:
    """t in [0, 1] with density proportional to cosh(a (t - 1/2)), by its inverse CDF:
    F(t) = (sinh(a (t - 1/2)) + sinh(a / 2)) / (2 sinh(a / 2))."""
    u = torch.rand(n, generator=gen, device="cpu")
    s = math.sinh(a / 2)
    return (0.5 + torch.asinh((2 * u - 1) * s) / a).clamp(1e-5, 1 - 1e-5)


def pseudo_huber(diff: torch.Tensor, c: float) -> torch.Tensor:
    """sqrt(|diff|^2 + c^2) - c per sample (B, ...) -> (B,): quadratic near 0, linear far out."""
    sq = diff.flatten(1).pow(2).sum(dim=1)
    return torch.sqrt(sq + c * c) - c


class RectifiedFlowPlusPlus(Method):
    name = "rfpp"
    label = "one-step (2-RF++: U-shaped t, pseudo-Huber)"
    summary = "2-rectified-flow++: all t, U-shaped (a = 4), pseudo-Huber, one Euler step"
    Knobs = RFPPKnobs

    def draw(self, cfg, n, gen):
        return Times(u_shaped_t(n, self.knobs(cfg).u_shape_a, gen))

    def loss(self, cfg, calls: StepCalls, x0, x1, times, gen=None):
        t = times.t
        c = self.knobs(cfg).huber_c * math.sqrt(x1[0].numel())
        return pseudo_huber(calls.f(interpolate(x0, x1, t), t) - (x1 - x0), c).mean()

    def time_words(self, flow):
        return "U-shaped on [0, 1] (a = method_config.u_shape_a), pseudo-Huber"


METHOD = RectifiedFlowPlusPlus()
