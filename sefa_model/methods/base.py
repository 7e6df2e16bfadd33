"""What a method is: one way of training and sampling a policy, behind one small interface.

A method says what a training step fits (`pairs`: expert windows with fresh noise, or stored
couplings), how it draws the step's times (`draw`), its loss (`loss`), how it samples (a fixed
Euler sampler for students, any solver for flows), its NFE and its label in tables. Everything
else (the loop, the data, checkpoints, the stage graph, evaluation) asks the method and never
branches on the way a policy was trained. The registry is `sefa_model.methods`; adding a method
is one module (docs/extending.md).

Shapes: x0, x1 (B, T, Da) normalized chunks; t, d (B,) in [0, 1]; a model call
`f(x, t, d=None) -> (B, T, Da)` is one network evaluation with the observation already bound
(`d` is the step size for methods with a step input, else ignored).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable, ClassVar, Literal

import torch

if TYPE_CHECKING:
    from sefa_model.config import FlowConfig, TrainConfig

# f(x (B, T, Da), t (B,), d (B,) | None) -> (B, T, Da)
ModelCall = Callable[..., torch.Tensor]


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
    """The interface. Subclasses set the class attributes and override what differs."""

    name: ClassVar[str]  # the registry key: `sefa distill --method NAME`, `distill.method`
    label: ClassVar[str]  # a table's name for a policy trained this way
    summary: ClassVar[str]  # one line for `sefa distill --help` and docs
    pairs: ClassVar[Literal["expert", "couplings"]] = "couplings"
    student: ClassVar[bool] = True  # sampled by a fixed Euler sampler (its NFE), not any solver
    step_input: ClassVar[bool] = False  # the network takes the step size d (zero-initialised)
    needs_teacher: ClassVar[bool] = False  # its loss calls the frozen initial policy

    # ------------------------------------------------------------------ what a step fits
    def draw(self, cfg: "TrainConfig", n: int, gen: torch.Generator) -> Times:
        """The training times of a global batch of n, from the step's generator alone."""
        raise NotImplementedError

    def loss(self, calls: StepCalls, x0: torch.Tensor, x1: torch.Tensor, times: Times,
             gen: torch.Generator | None = None) -> torch.Tensor:
        raise NotImplementedError

    # ------------------------------------------------------------------ how it samples
    def sampler(self, flow: "FlowConfig") -> tuple[str, int] | None:
        """The fixed (solver, steps) a student samples with; None: any solver (a flow)."""
        return ("euler", flow.steps or 1) if self.student else None

    def sample_step(self, flow: "FlowConfig", steps: int) -> float | None:
        """The step size d handed to the network while sampling with `steps` Euler steps."""
        if not self.step_input:
            return None
        t0, t1 = flow.time_span
        return (t1 - t0) / steps

    def check(self, flow: "FlowConfig") -> None:
        """Refuse a flow config this method cannot train or sample (a ConfigError)."""
        from sefa_data.errors import ConfigError

        fixed = self.sampler(flow)
        if fixed is not None and (flow.solver, flow.steps) != fixed:
            raise ConfigError(f"a policy trained as {self.name} samples with {fixed[1]} Euler "
                              f"step(s); got solver {flow.solver} steps {flow.steps}", key="solver")

    def time_words(self, flow: "FlowConfig") -> str:
        """Where the velocity is trained, in words (config.json's flow_convention.t_train)."""
        raise NotImplementedError

    # ------------------------------------------------------------------ the student's config
    def student_flow(self, steps: int) -> dict:
        """The FlowConfig settings of a student trained this way for `steps` sampler steps."""
        return {"solver": "euler", "steps": steps, "t_eps": 0.0}
