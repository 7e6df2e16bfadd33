"""What a method is: one way of training and sampling a policy, behind one small interface.

A method owns everything that varies with the way a policy was trained: what a training step
fits (`pairs`: expert windows with fresh noise, or stored couplings), how it draws the step's
times (`draw`), its loss (`loss`), how it samples (`sample`: an ODE solve of the velocity for
every flow, a fixed Euler sampler for students, the reverse process for the diffusion baseline)
and which samplers it accepts (`resolve_solver`), its own settings (`Knobs`, kept in the train
config's `method_config`, so in the cache key and in config.json), the config a stage derives
from its teacher's (`derive`), and its names in tables (`label`, `table_name`). Everything else
(the loop, the data, checkpoints, the stage graph, evaluation) asks the method and never
branches on the way a policy was trained. The registry is `sefa_model.methods`; adding a method
is one module (docs/extending.md).

Shapes: x0, x1 (B, T, Da) normalized chunks; t, d (B,) in [0, 1]; a model call
`f(x, t, d=None) -> (B, T, Da)` is one network evaluation with the observation already bound
(`d` is the step size for methods with a step input, else ignored).

This module imports no torch at import time: a config naming the default student is checked
without loading the methods (and torch) at all.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable, ClassVar, Literal

from sefa_data.errors import ConfigError, SefaInputError

if TYPE_CHECKING:
    import torch

    from sefa_model.config import FlowConfig, TrainConfig
    from sefa_model.flow.cuda_graphs import FieldGraphs
    from sefa_model.flow.solvers import SolveResult

    # f(x (B, T, Da), t (B,), d (B,) | None) -> (B, T, Da)
    ModelCall = Callable[..., torch.Tensor]

# What every stage trained from another policy's weights sets first (its own overrides come
# after): the encoder of the policy it starts from stays fixed, its features computed once.
DERIVED_STAGE_DEFAULTS = ["training.freeze_encoder=true"]


@dataclass
class StepCalls:
    """The network as a loss may call it. `f` carries gradients (through DDP and compile);
    `target` is the same weights without gradients, for targets a method builds from the
    model itself (self-consistency, mean flow's derivative); `teacher`, when the method asks
    for one, the frozen initial policy (the base flow a student distils)."""

    f: ModelCall
    target: ModelCall | None = None
    teacher: ModelCall | None = None
    # the same calls for the batch rows `mask` selects (B,) bool: a target built on a share of
    # the batch (shortcut's self-consistency) evaluates only those rows
    rows: Callable[[torch.Tensor], "StepCalls"] | None = None


@dataclass(frozen=True)
class Times:
    """A step's training times: t (B,), and the step size d (B,) for methods with a step input."""

    t: torch.Tensor
    d: torch.Tensor | None = None


class Method:
    """The interface. Subclasses set the class attributes and override what differs; the
    defaults are a rectified flow's (an ODE solve of the velocity from noise at t0 to data)."""

    name: ClassVar[str]  # the registry key: `sefa distill --method NAME`, `distill.method`
    label: ClassVar[str]  # a table's name for a policy trained this way
    summary: ClassVar[str]  # one line for `sefa distill --help` and docs
    pairs: ClassVar[Literal["expert", "couplings"]] = "couplings"
    student: ClassVar[bool] = True  # sampled by a fixed Euler sampler (its NFE), not any solver
    step_input: ClassVar[bool] = False  # the network takes the step size d (zero-initialised)
    needs_teacher: ClassVar[bool] = False  # its loss calls the frozen initial policy
    # its chunks come from integrating a velocity field from noise: it can make reflow's
    # couplings, be unrolled into an exported graph and be sampled by any ODE solver
    solves_ode: ClassVar[bool] = True
    # the method whose loss validation reports, so that every policy of one family compares
    yardstick: ClassVar[str] = "flow"
    # its settings: a dataclass (strict keys, ranges with sefa_data.ranges.knob) read from the
    # train config's `method_config`; None: it has none
    Knobs: ClassVar[type | None] = None

    # ------------------------------------------------------------------ what a step fits
    def draw(self, cfg: "TrainConfig", n: int, gen: "torch.Generator") -> Times:
        """The training times of a global batch of n, from the step's generator alone."""
        raise NotImplementedError

    def loss(self, cfg: "TrainConfig", calls: StepCalls, x0: "torch.Tensor", x1: "torch.Tensor",
             times: Times, gen: "torch.Generator | None" = None) -> "torch.Tensor":
        """The step's scalar loss; `cfg` carries the method's knobs (`self.knobs(cfg)`)."""
        raise NotImplementedError

    def kind(self) -> str:
        """What a training on expert windows records as its kind (couplings name their own)."""
        return "one_step" if self.student else "base_flow"

    def knobs(self, cfg: "TrainConfig | None") -> Any:
        """The method's settings from `cfg.method_config`, checked (None: it has none); with no
        config, its defaults."""
        if cfg is None:
            return None if self.Knobs is None else self.Knobs()
        if self.Knobs is None:
            if cfg.method_config:
                raise ConfigError(f"method {self.name} has no settings; got "
                                  f"{', '.join(sorted(cfg.method_config))}", key="method_config")
            return None
        from sefa_data.config_io import from_dict

        return from_dict(self.Knobs, dict(cfg.method_config), prefix="method_config")

    # ------------------------------------------------------------------ the network
    def network(self, model, x: "torch.Tensor", t: "torch.Tensor", cond: "torch.Tensor",
                d: "torch.Tensor | None" = None) -> "torch.Tensor":
        """One evaluation of the network as this method reads it: a velocity."""
        return model.velocity(x, t, cond, d)

    def probe_time(self, cfg: "TrainConfig", device) -> "torch.Tensor":
        """A time input (1,) for timing one network evaluation on its own."""
        import torch

        return torch.zeros(1, device=device)

    # ------------------------------------------------------------------ how it samples
    def solvers(self) -> tuple[str, ...]:
        from sefa_model.flow.solvers import METHODS

        return METHODS

    def default_solver(self, cfg: "TrainConfig") -> tuple[str, int | None]:
        """The checkpoint's own sampling setting."""
        return cfg.flow.solver, cfg.flow.steps

    def sampler(self, flow: "FlowConfig") -> tuple[str, int] | None:
        """The fixed (solver, steps) a student samples with; None: any solver (a flow)."""
        return ("euler", flow.steps or 1) if self.student else None

    def sample_step(self, flow: "FlowConfig", steps: int) -> float | None:
        """The step size d handed to the network while sampling with `steps` Euler steps."""
        if not self.step_input:
            return None
        t0, t1 = flow.time_span
        return (t1 - t0) / steps

    def trained_words(self, flow: "FlowConfig", k: int) -> str:
        """How a k-step student was trained, for the line that refuses another sampler."""
        return f"as a {k}-step {self.name} student"

    def resolve_solver(self, cfg: "TrainConfig", solver: str | None, steps: int | None
                       ) -> tuple[str, int | None]:
        """The (solver, steps) to use, with the checkpoint's defaults filled in and the choice
        checked against the method; adaptive solvers take tolerances, never a step count."""
        from sefa_model.flow.solvers import ADAPTIVE

        default, default_steps = self.default_solver(cfg)
        solver = solver or default
        valid = self.solvers()
        if solver not in valid:
            raise SefaInputError(f"solver '{solver}' does not apply to a {self.family(cfg)} policy "
                                 f"(valid: {', '.join(valid)})", key="--solver")
        fixed = self.sampler(cfg.flow)
        k = fixed[1] if fixed else None
        # a student told its step size (shortcut, mean flow) takes Euler steps of any size
        if k is not None and self.step_input and solver == "euler":
            k = steps or k
        if k is not None and (solver, steps or k) != ("euler", k):
            raise SefaInputError(f"this policy was trained {self.trained_words(cfg.flow, k)}: it "
                                 f"samples with {'one Euler step' if k == 1 else f'{k} Euler steps'}"
                                 f", not {solver}" + (f"-{steps}" if steps else ""), key="--solver")
        if solver in ADAPTIVE:
            return solver, None
        if steps is None:
            steps = default_steps if solver == default else self.fallback_steps(cfg)
        if steps is None:
            raise SefaInputError(f"solver '{solver}' needs a step count (--steps)", key="--steps")
        return solver, steps

    def fallback_steps(self, cfg: "TrainConfig") -> int | None:
        """The step count of a fixed-step sampler asked for without one (None: ask for it)."""
        return None

    def family(self, cfg: "TrainConfig") -> str:
        """The word a sampler's refusal names the policy by."""
        return "flow"

    def sample(self, model, cond: "torch.Tensor", noise: "torch.Tensor", solver: str,
               steps: int | None, *, generator: "torch.Generator | None" = None,
               rtol: float | None = None, atol: float | None = None,
               graphs: "FieldGraphs | None" = None) -> "SolveResult":
        """cond (B, D), noise (B, T, Da) -> the normalized chunk (B, T, Da) and its NFE: the
        velocity integrated over `FlowConfig.time_span` by the resolved solver. With `graphs`
        (on CUDA) the velocity replays a CUDA graph at every evaluation of a whole-batch solver
        (reflow's batched solves); the per-sample solvers, whose batch shrinks, stay eager."""
        from sefa_model.flow.solvers import WHOLE_BATCH, solve

        flow = model.cfg.flow
        t0, t1 = flow.time_span
        field = model.velocity
        d = self.sample_step(flow, steps) if steps else None
        if d is not None:  # a student with a step input is told the step it takes
            field = lambda x, t, c: model.velocity(x, t, c, d)  # noqa: E731
        if graphs is not None and solver in WHOLE_BATCH:
            field = graphs.field(field, tag=d)
        return solve(field, noise, solver, t0=t0, t1=t1, steps=steps,
                     rtol=flow.rtol if rtol is None else rtol,
                     atol=flow.atol if atol is None else atol, cond=cond)

    def solve_progress(self, cfg: "TrainConfig", calls: int, t_in: "torch.Tensor"
                       ) -> tuple[int, int]:
        """(done, total) of a batched solve after `calls` network evaluations, the last one at
        the head's time input `t_in`: a flow's time (in thousandths of [t_eps, 1]); the furthest
        row tells how far the solve is."""
        return int(round(1000 * float(t_in.max()) / cfg.flow.time_scale)), 1000

    # ------------------------------------------------------------------ checks and records
    def check(self, flow: "FlowConfig") -> None:
        """Refuse a flow config this method cannot train or sample (a ConfigError)."""
        fixed = self.sampler(flow)
        if fixed is not None and (flow.solver, flow.steps) != fixed:
            raise ConfigError(f"a policy trained as {self.name} samples with {fixed[1]} Euler "
                              f"step(s); got solver {flow.solver} steps {flow.steps}", key="solver")

    def time_words(self, flow: "FlowConfig") -> str:
        """Where the velocity is trained, in words (config.json's flow_convention.t_train)."""
        raise NotImplementedError

    def convention(self, cfg: "TrainConfig") -> dict:
        """What a checkpoint's config.json records of how its network's inputs are read."""
        convention = {"flow_convention": cfg.flow.convention()}
        if cfg.method is not None:  # older configs name no method: their t_train says it
            convention["flow_convention"]["t_train"] = self.time_words(cfg.flow)
        return convention

    def table_name(self, couplings: str) -> str:
        """A coupling student's name in tables, from what its couplings were
        (`SeFA one-step`, `reflow one-step (no alignment)`, ...)."""
        return f"{couplings}, {self.name}"

    # ------------------------------------------------------------------ the config it trains
    def student_flow(self, steps: int) -> dict:
        """The FlowConfig settings of a student trained this way for `steps` sampler steps."""
        return {"solver": "euler", "steps": steps, "t_eps": 0.0}

    def derive(self, base: "TrainConfig", overrides: list[str], *, train_steps: int | None = None,
               steps: int = 1) -> "TrainConfig":
        """The config of a policy trained this way from `base`'s weights (a student, or a
        reflowed flow): the base config, encoder frozen, sampled by `steps` Euler steps from
        t = 0, the method and its settings recorded. `train_steps`: its training length (None:
        the overrides', else the base flow's)."""
        from sefa_data.config_io import to_dict

        cfg = derived_config(base, overrides, train_steps, **self.student_flow(steps))
        cfg.method = self.name
        if self.Knobs is not None:  # resolved, so that a default's change is a new cache key
            cfg.method_config = to_dict(self.knobs(cfg))
        self.check(cfg.flow)
        return cfg


def derived_config(base: "TrainConfig", overrides: list[str], max_steps: int | None = None,
                   **flow) -> "TrainConfig":
    """`base` with the derived stages' defaults, then `overrides`, then the flow settings."""
    from sefa_data.config_io import apply_overrides, from_dict
    from sefa_model.config import TrainConfig, config_to_dict

    # a derived stage sets its own length: the base flow's schedule length does not carry over
    data = config_to_dict(base)
    data["training"]["lr_decay_steps"] = None
    data = apply_overrides(data, DERIVED_STAGE_DEFAULTS + list(overrides)
                           + ([] if max_steps is None else [f"training.max_steps={max_steps}"]))
    data["flow"] = {**data["flow"], **flow}
    return from_dict(TrainConfig, data)
