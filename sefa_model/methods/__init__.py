"""The registry of methods: every way sefa trains and samples a policy, one module each.

    flow          the base rectified flow                 (sefa train)
    ddpm          the diffusion baseline                  (sefa train --objective ddpm)
    reflow        a reflowed flow, rounds >= 2            (sefa reflow --iters k)
    reference     the reference code's student            (sefa distill --method reference)
    rfpp          2-rectified-flow++                      (sefa distill --method rfpp)
    mean_flow     a mean-flow student, fresh noise        (sefa distill --method mean_flow)
    shortcut      a shortcut student, fresh noise         (sefa distill --method shortcut)

`method_of(cfg)` is the one place that says which method a config trains: `cfg.method` when
set, else what the config's older fields meant (objective ddpm; flow.t_train uniform for a flow,
start / grid for the reference student), so checkpoints written before methods existed load
and sample as they did. A new method: a module with a `Method` subclass, registered with
`register` (docs/extending.md).
"""

from __future__ import annotations

import difflib
from typing import TYPE_CHECKING

from sefa_model.methods.base import Method, StepCalls, Times

if TYPE_CHECKING:
    from sefa_model.config import TrainConfig

_REGISTRY: dict[str, Method] = {}
STUDENTS_DEFAULT = "reference"


def register(method: Method) -> Method:
    """Add a method under its name (a name taken by another method is an error)."""
    old = _REGISTRY.get(method.name)
    if old is not None and type(old) is not type(method):
        raise ValueError(f"method name '{method.name}' is taken by {type(old).__name__}")
    _REGISTRY[method.name] = method
    return method


BUILTIN = ("flow", "diffusion", "reflowed_flow", "reference", "rfpp", "mean_flow", "shortcut")


def _builtin() -> None:
    """The built-in methods in table order, then every other module of this folder that
    defines METHOD (a method added in one file), then the `sefa.methods` entry points of
    installed packages."""
    import importlib
    import pkgutil
    from importlib.metadata import entry_points

    others = sorted(m.name for m in pkgutil.iter_modules(__path__)
                    if m.name not in BUILTIN and m.name != "base")
    for name in (*BUILTIN, *others):
        method = getattr(importlib.import_module(f"{__name__}.{name}"), "METHOD", None)
        if isinstance(method, Method):
            register(method)
    for ep in entry_points(group="sefa.methods"):
        register(ep.load())


def names(students_only: bool = False) -> list[str]:
    if not _REGISTRY:
        _builtin()
    return [n for n, m in _REGISTRY.items() if m.student or not students_only]


def get(name: str, key: str = "method") -> Method:
    """The method called `name`; an unknown name is one line listing the valid ones, nearest first."""
    if not _REGISTRY:
        _builtin()
    if name not in _REGISTRY:
        from sefa_data.errors import ConfigError

        near = difflib.get_close_matches(name, list(_REGISTRY), n=len(_REGISTRY), cutoff=0)
        raise ConfigError(f"unknown method '{name}' (valid: {', '.join(near)})", key=key)
    return _REGISTRY[name]


def method_of(cfg: "TrainConfig") -> Method:
    """The method a config trains and samples with (see the module docstring)."""
    if cfg.method is not None:
        return get(cfg.method)
    if cfg.objective == "ddpm":
        return get("ddpm")
    return get("flow" if cfg.flow.t_train == "uniform" else "reference")


__all__ = ["Method", "StepCalls", "Times", "get", "method_of", "names", "register"]
