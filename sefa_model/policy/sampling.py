"""Which sampler a policy uses: the checkpoint's own setting, or one asked for, checked by its
method (`Method.resolve_solver`: a flow takes any ODE solver, euler, midpoint, rk4, rk45, rk45-ps,
dop853-ps; a student its fixed Euler steps; the diffusion baseline its reverse process, ddpm or
ddim). The sampling itself is `FlowPolicyModel.sample`.
"""

from __future__ import annotations

from contextlib import contextmanager
from typing import Callable, Iterator

from sefa_model.config import TrainConfig
from sefa_model.methods import method_of


def default_solver(cfg: TrainConfig) -> tuple[str, int | None]:
    """The checkpoint's own sampling setting."""
    return method_of(cfg).default_solver(cfg)


def resolve_solver(cfg: TrainConfig, solver: str | None, steps: int | None) -> tuple[str, int | None]:
    """The (solver, steps) to use, with the checkpoint's defaults filled in and the choice
    checked against its method; adaptive solvers take tolerances, never a step count."""
    return method_of(cfg).resolve_solver(cfg, solver, steps)


def solver_label(cfg: TrainConfig, solver: str | None, steps: int | None) -> str:
    """A setting as tables print it: rk45, euler-1, ddim-10, ddpm-100."""
    solver, steps = resolve_solver(cfg, solver, steps)
    return solver if steps is None else f"{solver}-{steps}"


@contextmanager
def watching_solves(model, on_call: Callable[[int, int, int], None]) -> Iterator[None]:
    """Within the block, `on_call(calls, done, total)` after every network evaluation: how far
    the batched solve running is, as the model's method reads it from the head's time input (a
    flow: its time, the furthest row's, in thousandths of [t_eps, 1]; the diffusion baseline:
    its step count), never going back (a rejected adaptive step retries from an earlier time;
    going back, a bar would read it as a new run and lose its rate and ETA).
    A replayed CUDA graph calls no module, so it reports nothing."""
    import torch

    method, cfg = model.method, model.cfg
    total = method.solve_progress(cfg, 0, torch.zeros(1))[1]
    state = {"calls": 0, "done": 0}

    def hook(module, args, output) -> None:
        state["calls"] += 1
        done, _ = method.solve_progress(cfg, state["calls"], args[1])  # args[1]: the head's time
        state["done"] = max(state["done"], min(done, total))
        on_call(state["calls"], state["done"], total)

    handle = model.head.register_forward_hook(hook)
    try:
        yield
    finally:
        handle.remove()
