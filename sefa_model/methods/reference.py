"""The reference code's student (SeFA's `reflow_t_schedule: t0`): MSE on the stored couplings
at t = 0 only, so that one Euler step from the noise lands on the target. With k sampler steps,
trained at the k times k Euler steps visit (t_eps + i (1 - t_eps) / k): on a straight coupling
the velocity is x1 - x0 at every one of them."""

from __future__ import annotations

import torch

from sefa_model.methods.base import Method, StepCalls, Times
from sefa_model.flow.rectified_flow import euler_grid_t, flow_loss


class ReferenceStudent(Method):
    name = "reference"
    label = "one-step (reference: MSE at t = 0)"
    summary = "the reference code's student: MSE at t = 0 (k steps: at the k Euler times)"

    def draw(self, cfg, n, gen):
        flow = cfg.flow
        if flow.t_train == "grid":
            return Times(euler_grid_t(n, flow.t_eps, flow.steps, gen))
        return Times(torch.full((n,), float(flow.t_eps)))

    def loss(self, cfg, calls: StepCalls, x0, x1, times, gen=None):
        return flow_loss(lambda x, t: calls.f(x, t), x0, x1, times.t)

    def check(self, flow):
        flow.validate()  # its t_train checks are this method's: configs without a method name use them

    def time_words(self, flow):
        if flow.t_train == "grid":
            return f"the {flow.steps} Euler times from {flow.t_eps:g} ({flow.steps} steps)"
        return f"{flow.t_eps:g} (one step)"

    def student_flow(self, steps):
        return {**super().student_flow(steps), "t_train": "start" if steps == 1 else "grid"}


METHOD = ReferenceStudent()
