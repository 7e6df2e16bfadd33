"""A shortcut student (Frans et al. 2024, "One Step Diffusion via Shortcut Models"; SnapFlow's
self-distillation for robot policies), initialised from the base flow, on expert windows with
fresh noise: the network takes the step size d, and a step of 2d must equal two steps of d
taken with its own (no-gradient) predictions,

    s(z_t, t, 2d) = 1/2 s(z_t, t, d) + 1/2 s(z_t + d s(z_t, t, d), t + d, d),

from d = 0 (the frozen base flow's velocity, distilled) up to d = 1 (one step from the noise).
As in the paper's code, a quarter of the batch carries self-consistency targets at
d in {1/128, ..., 1/2} (so 2d up to 1, on times where the doubled step fits), the rest flow
matching at d = 0."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from sefa_data.ranges import UNIT, count, knob
from sefa_model.flow.rectified_flow import interpolate
from sefa_model.methods.base import Method, StepCalls, Times


@dataclass
class ShortcutKnobs:
    """The shortcut model's settings (`method_config.levels=...` in the train overrides)."""

    bootstrap_share: float = knob(0.25, UNIT)  # shortcut models' bootstrap_every = 4
    levels: int = knob(7, count(1, 30))  # d = 2^-levels .. 2^-1, doubled to 2^-(levels-1) .. 1


def shortcut_times(n: int, gen: torch.Generator, bootstrap_share: float = 0.25,
                   levels: int = 7) -> Times:
    """d = 0 for 1 - bootstrap_share of the batch (t uniform); the rest: 2d = 2^-j, j = 0..levels-1,
    and t on the grid of multiples of 2d that leaves room for the doubled step. Returns d as the
    doubled step (what the network is asked for), 0 for flow matching."""
    u = torch.rand(n, generator=gen)
    boot = torch.rand(n, generator=gen) < bootstrap_share
    level = torch.randint(0, levels, (n,), generator=gen)
    big = 2.0 ** (-level.float())  # the doubled step 2d in (0, 1]
    slots = (1.0 / big).round()
    t_grid = torch.floor(u * slots) * big
    return Times(torch.where(boot, t_grid, u), torch.where(boot, big, torch.zeros_like(u)))


class ShortcutStudent(Method):
    name = "shortcut"
    label = "one-step (shortcut, fresh noise)"
    summary = "shortcut model from the base flow: self-consistent steps of size d, one step"
    pairs = "expert"
    step_input = True
    needs_teacher = True
    Knobs = ShortcutKnobs

    def draw(self, cfg, n, gen):
        k = self.knobs(cfg)
        return shortcut_times(n, gen, k.bootstrap_share, k.levels)

    def loss(self, cfg, calls: StepCalls, x0, x1, times, gen=None):
        t, big = times.t, times.d
        z = interpolate(x0, x1, t)
        boot = big > 0
        with torch.no_grad():
            target = calls.teacher(z, t)  # d = 0: the base flow's velocity
            if bool(boot.any()):
                zb, tb, h = z[boot], t[boot], big[boot] / 2
                target_b = calls.rows(boot).target
                s1 = target_b(zb, tb, h)
                s2 = target_b(zb + h.view(-1, 1, 1) * s1, tb + h, h)
                target[boot] = 0.5 * (s1 + s2)
        return (calls.f(z, t, big) - target).pow(2).mean()

    def time_words(self, flow):
        return "shortcut: d = 0 on U[0, 1] for 3/4, self-consistency at 2d = 2^-j for 1/4"


METHOD = ShortcutStudent()
