"""The registry of methods: every way sefa trains and samples a policy, one module each.

    flow          the base rectified flow                 (sefa train)
    ddpm          the diffusion baseline                  (sefa train --objective ddpm)
    reflow        a reflowed flow, rounds >= 2            (sefa reflow --iters k)
    reference     the reference code's student            (sefa distill --method reference)
    rfpp          2-rectified-flow++                      (sefa distill --method rfpp)
    mean_flow     a mean-flow student, fresh noise        (sefa distill --method mean_flow)
    shortcut      a shortcut student, fresh noise         (sefa distill --method shortcut)

`method_of(cfg)` is the one place that says which method a config trains, and checks the
config against it: `cfg.method` when set, else what the config's older fields meant (objective
ddpm; flow.t_train uniform for a flow, start / grid for the reference student), so checkpoints
written before methods existed load and sample as they did. A stage's config comes from its
method too (`student_config`, `reflowed_flow_config`).

A new method is a module with a `Method` subclass and `METHOD = TheClass()`: in this folder, or
in a package of your own that names it under the `sefa.methods` entry point, so that every
process that loads one of its checkpoints (`sefa eval`, `sefa serve`, `sefa export`) finds it
(docs/extending.md). A plugin that fails to import is left out with one warning; an error
raised inside a plugin's method is reported as that plugin's, in one line.
"""

from __future__ import annotations

import difflib
import functools
import sys
from typing import TYPE_CHECKING

from sefa_data.errors import ConfigError, SefaInputError
from sefa_model.methods.base import Method, StepCalls, Times

if TYPE_CHECKING:
    from sefa_model.config import TrainConfig

_REGISTRY: dict[str, Method] = {}
# the student `sefa distill` trains unless told otherwise: named here only, so that a config
# naming it is checked without loading every method (and torch)
STUDENTS_DEFAULT = "reference"

BUILTIN = ("flow", "diffusion", "reflowed_flow", "reference", "rfpp", "mean_flow", "shortcut")
NOT_METHODS = ("base",)
# what a plugin's method may raise for sefa to report as its own; anything else is the plugin's
GUARDED = ("draw", "loss", "network", "sample", "resolve_solver", "check", "derive", "knobs",
           "time_words", "convention", "solve_progress", "probe_time")


def register(method: Method, origin: str | None = None) -> Method:
    """Add a method under its name (a name taken by another method is an error). `origin`:
    the package an entry point came from; its method's errors are then reported as its own."""
    old = _REGISTRY.get(method.name)
    if old is not None and type(old) is not type(method):
        raise ValueError(f"method name '{method.name}' is taken by {type(old).__name__}")
    if origin is not None:
        for name in GUARDED:
            setattr(method, name, _guarded(getattr(method, name), method.name, origin))
    _REGISTRY[method.name] = method
    return method


def _guarded(fn, name: str, origin: str):
    """`fn`, with any error that is not one of sefa's own clear lines turned into one that
    names the plugin: the fault is the plugin's, not sefa's."""
    @functools.wraps(fn)
    def call(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except SefaInputError:
            raise
        except Exception as e:  # noqa: BLE001 - any fault of third-party code, named as such
            raise SefaInputError(f"method '{name}' from the plugin {origin} failed in "
                                 f"{fn.__name__}: {type(e).__name__}: {e}") from e
    return call


def _builtin() -> None:
    """The built-in methods in table order, then every other module of this folder that
    defines METHOD (a method added in one file), then the `sefa.methods` entry points of
    installed packages."""
    import importlib
    import pkgutil

    others = sorted(m.name for m in pkgutil.iter_modules(__path__)
                    if m.name not in BUILTIN and m.name not in NOT_METHODS)
    for name in (*BUILTIN, *others):
        method = getattr(importlib.import_module(f"{__name__}.{name}"), "METHOD", None)
        if isinstance(method, Method):
            register(method)
    _plugins()


def _plugins() -> None:
    """Each `sefa.methods` entry point, isolated: one that fails to load or is not a method
    is named in one warning on stderr and left out; the others and the built-ins still work."""
    from importlib.metadata import entry_points

    for ep in entry_points(group="sefa.methods"):
        origin = f"'{ep.value}'" + (f" (package {ep.dist.name})" if ep.dist else "")
        try:
            method = ep.load()
            if not isinstance(method, Method):
                raise TypeError(f"it is a {type(method).__name__}, not a sefa Method instance")
            register(method, origin=origin)
        except Exception as e:  # noqa: BLE001 - a broken plugin must not break every method
            print(f"warning: method plugin {ep.name} from {origin} left out: "
                  f"{type(e).__name__}: {e}", file=sys.stderr)


def names(students_only: bool = False) -> list[str]:
    if not _REGISTRY:
        _builtin()
    return [n for n, m in _REGISTRY.items() if m.student or not students_only]


def get(name: str, key: str = "method") -> Method:
    """The method called `name`; an unknown name is one line listing the valid ones, nearest first."""
    if not _REGISTRY:
        _builtin()
    if name not in _REGISTRY:
        near = difflib.get_close_matches(name, list(_REGISTRY), n=len(_REGISTRY), cutoff=0)
        raise ConfigError(f"unknown method '{name}' (valid: {', '.join(near)})", key=key)
    return _REGISTRY[name]


def student(name: str, key: str = "method") -> Method:
    """The student called `name`; an unknown name or a method that is not a student (it is
    trained by `sefa train` or `sefa reflow`) is one line listing the students."""
    if not _REGISTRY:
        _builtin()
    students = names(students_only=True)
    if name not in _REGISTRY:
        near = difflib.get_close_matches(name, students, n=len(students), cutoff=0)
        raise ConfigError(f"unknown student method '{name}' (students: {', '.join(near)})", key=key)
    if not _REGISTRY[name].student:
        raise ConfigError(f"'{name}' is not a student (students: {', '.join(students)})", key=key)
    return _REGISTRY[name]


def check_student(name: str, key: str = "method") -> None:
    """A config's student name, checked; the default is checked without loading a method."""
    if name != STUDENTS_DEFAULT:
        student(name, key)


def method_of(cfg: "TrainConfig") -> Method:
    """The method a config trains and samples with (see the module docstring), with the config
    checked against it: a method name given with the diffusion objective only if it is the
    diffusion baseline, the flow settings it samples with, its `method_config`."""
    if cfg.method is None:
        if cfg.method_config:
            raise ConfigError("method_config is set, but the config names no method", key="method")
        if cfg.objective == "ddpm":
            return get("ddpm")
        return get("flow" if cfg.flow.t_train == "uniform" else "reference")
    method = get(cfg.method, key="method")
    if method.solves_ode == (cfg.objective == "ddpm"):
        raise ConfigError(f"method {method.name} does not apply to objective {cfg.objective}",
                          key="method")
    try:
        method.check(cfg.flow)
    except ConfigError as e:
        raise ConfigError(e.what, key=f"flow.{e.key}") from None
    method.knobs(cfg)
    return method


def base_method(cfg: "TrainConfig") -> Method:
    """The method of a config `sefa train` trains (a base policy on expert chunks): a student
    or a reflowed flow named there is one line that says which command trains it."""
    method = method_of(cfg)
    if method.student or method.pairs == "couplings":
        what = "a student" if method.student else "trained on couplings"
        command = f"sefa distill --method {method.name}" if method.student else "sefa reflow"
        raise ConfigError(f"method '{method.name}' is {what}: `{command}` trains it from the base "
                          f"flow; `sefa train` trains a base policy (method flow or ddpm)",
                          key="method")
    return method


def student_config(base: "TrainConfig", overrides: list[str], train_steps: int | None = None,
                   steps: int = 1, method: str = STUDENTS_DEFAULT) -> "TrainConfig":
    """The student's config: encoder frozen, trained as `method` says and sampled by `steps`
    Euler steps from t = 0 (the checkpoint records both, so nothing else needs to know).
    `train_steps`: its training length (None: the overrides', else the base flow's)."""
    return student(method, key="distill.method").derive(base, overrides, train_steps=train_steps,
                                                        steps=steps)


def reflowed_flow_config(base: "TrainConfig", overrides: list[str], steps: int | None = None
                         ) -> "TrainConfig":
    """A reflowed flow (round >= 2): the base config, encoder frozen, t ~ U[t_eps, 1]."""
    return get("reflow").derive(base, overrides, train_steps=steps)


def distils_base_flow(name: str) -> bool:
    """Whether the student `name` reads no couplings: it distils the base flow on fresh noise."""
    return name != STUDENTS_DEFAULT and student(name).pairs == "expert"


def student_label(name: str | None, couplings: str | None) -> str:
    """A student as tables name it: a coupling student by its couplings (`couplings`, e.g.
    `SeFA one-step`) and its method, one distilled on fresh noise (`couplings` None) by its
    method's label."""
    method = get(name or STUDENTS_DEFAULT)
    return method.label if couplings is None else method.table_name(couplings)


__all__ = ["Method", "STUDENTS_DEFAULT", "StepCalls", "Times", "base_method", "check_student",
           "distils_base_flow", "get", "method_of", "names", "reflowed_flow_config", "register",
           "student", "student_config", "student_label"]
