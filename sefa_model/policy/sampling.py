"""Which sampler a policy uses: the checkpoint's own setting, or one asked for, checked against
its objective. A flow policy integrates its velocity field with an ODE solver (euler, midpoint,
rk4, rk45, rk45-ps, dop853-ps); the diffusion baseline runs its reverse process (ddpm, ddim).
The sampling itself is `FlowPolicyModel.sample`.
"""

from __future__ import annotations

from sefa_data.errors import SefaInputError
from sefa_model.config import TrainConfig
from sefa_model.methods import method_of
from sefa_model.flow.solvers import ADAPTIVE, METHODS

DIFFUSION_SAMPLERS = ("ddpm", "ddim")


def default_solver(cfg: TrainConfig) -> tuple[str, int | None]:
    """The checkpoint's own sampling setting."""
    if cfg.objective == "ddpm":
        return cfg.diffusion.sampler, cfg.diffusion.inference_steps
    return cfg.flow.solver, cfg.flow.steps


def resolve_solver(cfg: TrainConfig, solver: str | None, steps: int | None) -> tuple[str, int | None]:
    """The (solver, steps) to use, with the checkpoint's defaults filled in and the choice
    checked against the objective; adaptive solvers take tolerances, never a step count."""
    default, default_steps = default_solver(cfg)
    # a solver not asked for is the config's own: an error names that setting, not --solver
    key = "--solver" if solver else "diffusion.sampler" if cfg.objective == "ddpm" else "flow.solver"
    solver = solver or default
    valid = DIFFUSION_SAMPLERS if cfg.objective == "ddpm" else METHODS
    if solver not in valid:
        raise SefaInputError(f"solver '{solver}' does not apply to a {cfg.objective} policy "
                             f"(valid: {', '.join(valid)})", key=key)
    method = method_of(cfg)
    fixed = method.sampler(cfg.flow) if cfg.objective == "flow" else None
    k = fixed[1] if fixed else None
    # a student told its step size (shortcut, mean flow) takes Euler steps of any size
    if k is not None and method.step_input and solver == "euler":
        k = steps or k
    if k is not None and (solver, steps or k) != ("euler", k):
        name = method.name
        trained = (f"at t = {cfg.flow.t_eps:g} only (a one-step student)" if k == 1 and name == "reference"
                   else f"at the {k} times of {k} Euler steps (a {k}-step student)" if name == "reference"
                   else f"as a {k}-step {name} student")
        raise SefaInputError(f"this policy was trained {trained}: it samples with "
                             f"{'one Euler step' if k == 1 else f'{k} Euler steps'}, not {solver}"
                             + (f"-{steps}" if steps else ""),
                             key=key)
    if solver in ADAPTIVE:
        return solver, None
    if steps is None:
        steps = default_steps if solver == default else None
    if steps is None:
        steps = cfg.diffusion.inference_steps if cfg.objective == "ddpm" else None
    if steps is None:
        raise SefaInputError(f"solver '{solver}' needs a step count (--steps)", key="--steps")
    return solver, steps


def solver_label(cfg: TrainConfig, solver: str | None, steps: int | None) -> str:
    """A setting as tables print it: rk45, euler-1, ddim-10, ddpm-100."""
    solver, steps = resolve_solver(cfg, solver, steps)
    return solver if steps is None else f"{solver}-{steps}"
