"""The base rectified flow: expert chunks with fresh noise, t ~ U[t_eps, 1], MSE on the
velocity x1 - x0; sampled by any ODE solver (RK45 by default)."""

from __future__ import annotations

from sefa_model.methods.base import Method, StepCalls, Times
from sefa_model.flow.rectified_flow import flow_loss, sample_t


class BaseFlow(Method):
    name = "flow"
    label = "base flow"
    summary = "the base rectified flow: t ~ U[t_eps, 1], MSE on x1 - x0, any solver"
    pairs = "expert"
    student = False

    def draw(self, cfg, n, gen):
        return Times(sample_t(n, cfg.flow.t_eps, gen))

    def loss(self, cfg, calls: StepCalls, x0, x1, times, gen=None):
        return flow_loss(lambda x, t: calls.f(x, t), x0, x1, times.t)

    def time_words(self, flow):
        return f"U[{flow.t_eps:g}, 1]"


METHOD = BaseFlow()
