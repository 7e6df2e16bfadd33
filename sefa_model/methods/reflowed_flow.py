"""A reflowed flow (`sefa reflow --iters k`, rounds >= 2): the base flow's objective on stored
couplings (noise, generated or aligned chunk) instead of expert chunks with fresh noise."""

from __future__ import annotations

from sefa_model.methods.flow import BaseFlow


class ReflowedFlow(BaseFlow):
    name = "reflow"
    label = "reflowed flow"
    summary = "a reflowed flow: the base flow's objective on stored couplings, any solver"
    pairs = "couplings"


METHOD = ReflowedFlow()
