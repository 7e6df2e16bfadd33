"""Which sampler a policy uses: the checkpoint's own setting, or one asked for, checked by its
method (`Method.resolve_solver`: a flow takes any ODE solver, euler, midpoint, rk4, rk45, rk45-ps,
dop853-ps; a student its fixed Euler steps; the diffusion baseline its reverse process, ddpm or
ddim). The sampling itself is `FlowPolicyModel.sample`.
"""

from __future__ import annotations

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
