"""How a `step` connection turns predicted chunks into one action per control step.

Two ways, chosen per server (`sefa serve --execution`):

* `receding` (Diffusion Policy's execution): predict a chunk, execute its first `replan_every`
  actions open loop (default: all n_action_steps), then predict again from the newest frames.
  Cheap (one prediction per replan_every steps) but the step that replans waits for the policy,
  the others do not, and the action may jump where one chunk hands over to the next.
* `ensemble` (ACT's temporal ensembling): predict a chunk every `replan_every` steps (default
  1, as ACT) and execute, at each step, the weighted mean of every prediction made so far for
  that step. ACT's weights: w_i = exp(-k * i) with i = 0 for the oldest prediction (ACT's code
  uses k = 0.01; a larger k favours the older predictions more, k = 0 is the plain mean), then
  divided by their sum. Smoother hand-overs; a prediction on every step it replans.

A chunk here is the policy's `action` output: n_action_steps actions, the first for the step
whose frame it was predicted from.

The math is pure functions (`ensemble_weights`, `Ensembler`) so that it is tested on exact
arrays, not through a server.
"""

from __future__ import annotations

import collections
import math
from dataclasses import dataclass, field

import numpy as np

EXECUTIONS = ("receding", "ensemble")
DEFAULT_ENSEMBLE_K = 0.01  # ACT's value (act/imitate_episodes.py, temporal_agg)


def ensemble_weights(n: int, k: float) -> np.ndarray:
    """Normalized weights of n predictions of one step, oldest first: exp(-k * i) / sum."""
    w = np.exp(-k * np.arange(n, dtype=np.float64))
    return w / w.sum()


@dataclass
class Ensembler:
    """The chunks predicted so far that still cover a future step, each with the step it was
    predicted at. `add` a chunk predicted at step t, then `action(t)`."""
    k: float = DEFAULT_ENSEMBLE_K
    chunks: collections.deque = field(default_factory=collections.deque)  # (start step, chunk)

    def add(self, start: int, chunk: np.ndarray) -> None:
        self.chunks.append((start, np.asarray(chunk, dtype=np.float64)))

    def action(self, t: int) -> tuple[np.ndarray, int]:
        """The ensembled action for step t and how many predictions it averages. Chunks that
        end before t are dropped: they will never cover a step again."""
        while self.chunks and self.chunks[0][0] + len(self.chunks[0][1]) <= t:
            self.chunks.popleft()
        preds = [c[t - s] for s, c in self.chunks if s <= t]  # oldest first: added in order
        if not preds:
            raise ValueError(f"no prediction covers step {t}")
        w = ensemble_weights(len(preds), self.k)
        return np.tensordot(w, np.stack(preds), axes=1).astype(np.float32), len(preds)

    def clear(self) -> None:
        self.chunks.clear()


def default_replan_every(execution: str, n_action_steps: int) -> int:
    return n_action_steps if execution == "receding" else 1


def check_execution(execution: str, replan_every: int | None, ensemble_k: float,
                    n_action_steps: int) -> int:
    """-> replan_every, resolved; ValueError naming the option when a value cannot work with
    this policy (the options' ranges alone are pipelines/options.py's)."""
    if execution not in EXECUTIONS:
        raise ValueError(f"--execution: {execution!r} is not one of {', '.join(EXECUTIONS)}")
    if not (isinstance(ensemble_k, (int, float)) and math.isfinite(ensemble_k) and ensemble_k >= 0):
        raise ValueError(f"--ensemble-k: {ensemble_k!r} is not a finite number >= 0")
    if replan_every is None:
        return default_replan_every(execution, n_action_steps)
    if not 1 <= replan_every <= n_action_steps:
        # beyond n_action_steps a step would have no predicted action to execute
        raise ValueError(f"--replan-every: {replan_every} is outside 1..{n_action_steps} (the "
                         f"policy predicts n_action_steps = {n_action_steps} actions a chunk)")
    return replan_every


@dataclass
class Execution:
    """One connection's execution state: when to predict, what to execute. The server calls
    `due()`; if True it predicts and calls `add(chunk)`; then `next()` gives the action."""
    mode: str
    replan_every: int
    k: float = DEFAULT_ENSEMBLE_K
    t: int = 0  # the step about to be executed, from the episode's start
    last_plan: int | None = None
    queue: collections.deque = field(default_factory=collections.deque)
    ensembler: Ensembler = field(default_factory=Ensembler)

    def __post_init__(self):
        self.ensembler.k = self.k

    def reset(self) -> None:
        self.t, self.last_plan = 0, None
        self.queue.clear()
        self.ensembler.clear()

    def due(self) -> bool:
        return self.last_plan is None or self.t - self.last_plan >= self.replan_every

    def add(self, chunk: np.ndarray) -> None:
        self.last_plan = self.t
        if self.mode == "receding":
            self.queue.clear()
            self.queue.extend(chunk[:self.replan_every])
        else:
            self.ensembler.add(self.t, chunk)

    def next(self) -> tuple[np.ndarray, int]:
        """-> (the action for this step, a count: receding, the actions left queued; ensemble,
        the predictions averaged)."""
        if self.mode == "receding":
            action = self.queue.popleft()
            n = len(self.queue)
        else:
            action, n = self.ensembler.action(self.t)
        self.t += 1
        return action, n
