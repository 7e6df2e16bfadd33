"""The reference code's student (SeFA's `reflow_t_schedule: t0`): MSE on the stored couplings
at t = 0 only, so that one Euler step from the noise lands on the target. With k sampler steps,
trained at the k times k Euler steps visit (t_eps + i (1 - t_eps) / k): on a straight coupling
the velocity is x1 - x0 at every one of them."""

from __future__ import annotations

import torch

from sefa_model.methods.base import Method, StepCalls, Times, derived_config
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

    def derive(self, base, overrides, *, train_steps=None, steps=1):
        """Written as flow.t_train (start, or grid for k > 1 steps) without a method name, as
        before methods existed, so that its settings, cache key and results are the same."""
        return derived_config(base, overrides, train_steps, **self.student_flow(steps))

    def trained_words(self, flow, k):
        return (f"at t = {flow.t_eps:g} only (a one-step student)" if k == 1 else
                f"at the {k} times of {k} Euler steps (a {k}-step student)")

    def table_name(self, couplings):
        return couplings  # the reference code's student: the plain name


METHOD = ReferenceStudent()
