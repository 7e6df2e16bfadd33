"""A reflowed flow (`sefa reflow --iters k`, rounds >= 2): the base flow's objective on stored
couplings (noise, generated or aligned chunk) instead of expert chunks with fresh noise."""

from __future__ import annotations

from sefa_model.methods.base import derived_config
from sefa_model.methods.flow import BaseFlow


class ReflowedFlow(BaseFlow):
    name = "reflow"
    label = "reflowed flow"
    summary = "a reflowed flow: the base flow's objective on stored couplings, any solver"
    pairs = "couplings"

    def derive(self, base, overrides, *, train_steps=None, steps=1):
        """The base config, encoder frozen, t ~ U[t_eps, 1], the base flow's sampler; written
        without a method name, as before methods existed (its cache key and results kept)."""
        return derived_config(base, overrides, train_steps)


METHOD = ReflowedFlow()
