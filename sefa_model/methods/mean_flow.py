"""A mean-flow student (MeanFlow, Geng et al. 2025; MP1 for robot policies), distilled from the
base flow on expert windows with FRESH noise at every step: the network, given the step size d
as a second time input, learns the average velocity over [t, t + d],

    u(z_t, t, d) = 1/d * integral_t^{t+d} v(z_s, s) ds,

so that one step x1 = x0 + u(x0, 0, 1) is the whole ODE solve. The MeanFlow identity (the
derivative of d * u along the flow, the end time fixed) gives the regression target

    u_tgt = v(z_t, t) + d * (du/dt along (dz, dt, dd) = (v, 1, -1)),   stop-gradient,

computed with one forward-mode JVP of the network itself. v is the frozen base flow's velocity
(the marginal field a multi-step policy integrates), not the per-sample x1 - x0: the student
distils the teacher's flow, with the teacher's variance. Unlike the coupling students it sees
every training window with new noise at every step, as the base flow did, instead of K fixed
noises of a few thousand windows.

Settings as MeanFlow's: a share of the batch at d = 0 (plain flow matching of the teacher's
velocity), the rest on intervals from two sorted uniform times, a part of those the deployed
query itself (t = 0, d = 1); adaptive loss weight 1 / (|delta|^2 + c)^p (p = 1).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from sefa_data.ranges import NONNEGATIVE, POSITIVE, UNIT, knob
from sefa_model.flow.rectified_flow import interpolate
from sefa_model.methods.base import Method, StepCalls, Times


@dataclass
class MeanFlowKnobs:
    """MeanFlow's settings (`method_config.flow_share=...` in the student's train overrides)."""

    flow_share: float = knob(0.5, UNIT)  # d = 0: the instantaneous velocity (MeanFlow: 25-75 %)
    full_share: float = knob(0.25, UNIT)  # of the rest: (t = 0, d = 1), one-step sampling's query
    adaptive_p: float = knob(1.0, NONNEGATIVE)  # MeanFlow's adaptive weight (ImageNet: p = 1)
    adaptive_c: float = knob(1e-3, POSITIVE)


def interval_times(n: int, gen: torch.Generator, flow_share: float = 0.5,
                   full_share: float = 0.25) -> Times:
    """(t, d) with 0 <= t, t + d <= 1: d = 0 for `flow_share` of the batch, (0, 1) for
    `full_share` of the rest, two sorted uniforms for the others. Every draw comes from `gen`."""
    a, b = torch.rand(n, generator=gen), torch.rand(n, generator=gen)
    kind = torch.rand(n, generator=gen)
    t, end = torch.minimum(a, b), torch.maximum(a, b)
    flow = kind < flow_share
    full = (kind >= flow_share) & (kind < flow_share + (1 - flow_share) * full_share)
    t = torch.where(full, torch.zeros_like(t), torch.where(flow, a, t))
    end = torch.where(full, torch.ones_like(end), torch.where(flow, a, end))
    return Times(t, end - t)


def adaptive_mse(diff: torch.Tensor, p: float = 1.0, c: float = 1e-3) -> torch.Tensor:
    """MeanFlow's loss: |diff|^2 / sg(|diff|^2 + c)^p per sample, averaged."""
    sq = diff.flatten(1).pow(2).mean(dim=1)
    return (sq / (sq.detach() + c).pow(p)).mean()


class MeanFlowStudent(Method):
    name = "mean_flow"
    label = "one-step (mean flow, fresh noise)"
    summary = "MeanFlow distilled from the base flow: average velocity over [t, t + d], one step"
    pairs = "expert"
    step_input = True
    needs_teacher = True
    Knobs = MeanFlowKnobs

    def draw(self, cfg, n, gen):
        k = self.knobs(cfg)
        return interval_times(n, gen, k.flow_share, k.full_share)

    def loss(self, cfg, calls: StepCalls, x0, x1, times, gen=None):
        t, d = times.t, times.d
        z = interpolate(x0, x1, t)
        with torch.no_grad():
            v = calls.teacher(z, t)
            # d(u)/dt along the flow with the end time fixed: tangent (v, 1, -1) in (z, t, d)
            _, du = torch.func.jvp(lambda zz, tt, dd: calls.target(zz, tt, dd), (z, t, d),
                                   (v, torch.ones_like(t), -torch.ones_like(d)))
            target = v + d.view(-1, 1, 1) * du
        k = self.knobs(cfg)
        return adaptive_mse(calls.f(z, t, d) - target, k.adaptive_p, k.adaptive_c)

    def time_words(self, flow):
        return "intervals [t, t + d] of [0, 1] (mean flow), d = 0 for method_config.flow_share"


METHOD = MeanFlowStudent()
