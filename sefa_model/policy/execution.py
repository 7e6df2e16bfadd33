"""How predicted chunks become one action per control step: the one owner of chunk execution.

    settings = ExecutionSettings("receding", replan_every=4)
    executor = Executor.for_policy(policy, settings, seed=0)   # or Executor.load(checkpoint):
                                                               # the execution chosen for it
    executor.reset(seed)                       # a new episode (its noise seeded)
    action = executor.action(frame)            # the newest frame per key -> (Da,), every step

`sefa eval --env` (sefa_sim's rollouts), `sefa serve`'s `step` requests, the benchmarks and the
LeRobot integration all run their policy through an `Executor`; none executes a chunk itself.

The executor keeps the observation history (the last n_obs_steps frames, the episode's first
frame repeated until there are enough, as Diffusion Policy's MultiStepWrapper pads), decides
when to predict, draws the noise (one CPU generator per episode, so that a seed gives the same
actions in simulation and through the server), and picks the action. A decision at step t
samples `samples` chunks in one batched call; a chunk is the policy's whole `action_pred`
(horizon steps, the first for the oldest observed frame, so step t is index n_obs_steps - 1).

Modes (`mode`, every one predicting every `replan_every` steps, 1..n_action_steps):

* `receding` (Diffusion Policy): execute the chunk's next `replan_every` actions open loop, then
  predict again from the newest frames. replan_every = n_action_steps is the field's default.
* `ensemble` (ACT's temporal ensembling): execute, at each step, the weighted mean of every
  prediction made so far for that step, weights exp(-k i) with i = 0 the oldest (ACT: k = 0.01).
* `coherent` (Bidirectional Decoding's backward coherence, Liu et al. ICLR 2025): draw
  `samples` chunks and keep the one nearest to what the previous decision planned for the same
  steps (`coherence_cost`), then execute it as `receding` does.
* `bid` (Bidirectional Decoding): backward coherence keeps the most coherent third, and among
  those forward contrast picks the chunk nearest to the policy's other samples and farthest
  from a weaker policy's (`bid_choice`); needs the weaker policy (`weak`: the base flow at one
  Euler step costs one more batched evaluation).

The selection math is small pure functions on arrays (`coherence_cost`, `chunk_distances`,
`contrast_cost`, `bid_choice`, `ensemble_weights`) so that it is tested on exact numbers. Distances
are in action units, as the reference code measures them (per-step Euclidean norms).
"""

from __future__ import annotations

import collections
import json
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Literal

import numpy as np

from sefa_data.config_io import from_dict, to_dict
from sefa_data.errors import ConfigError, NonFiniteError, SefaInputError
from sefa_data.ranges import NONNEGATIVE, Range, check_ranges, count, knob

MODES = ("receding", "ensemble", "coherent", "bid")
SAMPLING_MODES = ("coherent", "bid")  # the modes that choose among several chunks
DEFAULT_ENSEMBLE_K = 0.01  # ACT's value (act/imitate_episodes.py, temporal_agg)
DEFAULT_DECAY = 0.9  # backward coherence's weight decay per step (the reference uses 0.5 to 0.99)
DEFAULT_SAMPLES = 16
CONTRAST_KEEP = 3  # bid: keep the samples // 3 most coherent before contrasting (BID's num_mode)
# the command-line option of each setting, for error lines
OPTION = {"mode": "--execution", "replan_every": "--replan-every", "samples": "--samples",
          "decay": "--decay", "ensemble_k": "--ensemble-k", "weak": "--weak"}
FIELD = {option: name for name, option in OPTION.items()}  # an option's setting, for files' keys


@dataclass(frozen=True)
class ExecutionSettings:
    """How `sefa eval --env` and `sefa serve` turn predicted chunks into one action per control
    step (unset: the execution chosen for each policy by `sefa choose-execution`, else
    receding horizon over n_action_steps)."""
    # receding (Diffusion Policy), ensemble (ACT), coherent or bid (Bidirectional Decoding)
    mode: Literal["receding", "ensemble", "coherent", "bid"] = "receding"
    # steps between predictions, 1..n_action_steps; None: n_action_steps for receding, else 1
    replan_every: int | None = knob(None, count(1, 100_000))
    # coherent, bid: chunks drawn per decision in one batched call; None: 16 (others: 1)
    samples: int | None = knob(None, count(1, 4096))
    # coherent, bid: backward coherence's weight decay per step
    decay: float = knob(DEFAULT_DECAY, Range(lo=0, hi=1, lo_open=True))
    # ensemble: ACT's k, weights exp(-k i) with i = 0 the oldest prediction
    ensemble_k: float = knob(DEFAULT_ENSEMBLE_K, NONNEGATIVE)
    # bid: the weaker policy, CHECKPOINT[@SOLVER-STEPS] (a workspace's base flow: train@euler-1)
    weak: str | None = None

    def is_default(self, n_action_steps: int) -> bool:
        """Whether these (resolved) settings are the field's execution, n_action_steps per
        prediction: what every result before executions were chosen ran."""
        return self == default_settings(n_action_steps)

    def resolved(self, n_action_steps: int, source: str | None = None) -> "ExecutionSettings":
        """The defaults filled in for a policy executing n_action_steps per chunk, checked:
        ConfigError naming the option (`--replan-every`, ...) when a value cannot work, or,
        for settings read from a file (`source`: sefa.yaml), the file and its key
        (`execution.replan_every`)."""
        if source is not None:
            try:
                return self.resolved(n_action_steps)
            except ConfigError as e:
                raise ConfigError(e.what, file=source,
                                  key=f"execution.{FIELD.get(e.key, e.key)}") from None
        self.check(n_action_steps)
        every, samples = self.replan_every, self.samples
        if every is None:
            every = n_action_steps if self.mode == "receding" else 1
        if samples is None:
            samples = DEFAULT_SAMPLES if self.mode in SAMPLING_MODES else 1
        out = replace(self, replan_every=every, samples=samples)
        out.check(n_action_steps)
        return out

    def check(self, n_action_steps: int) -> None:
        try:
            check_ranges(self)
        except ConfigError as e:  # named as the option is typed
            raise ConfigError(e.what, key=OPTION.get(e.key, e.key)) from None
        if self.mode not in MODES:
            raise ConfigError(f"not one of {', '.join(MODES)}: {self.mode!r}", key=OPTION["mode"])
        if self.replan_every is not None and not 1 <= self.replan_every <= n_action_steps:
            # beyond n_action_steps a step would have no predicted action to execute
            raise ConfigError(f"{self.replan_every} is outside 1..{n_action_steps} (the policy "
                              f"predicts n_action_steps = {n_action_steps} actions a chunk)",
                              key=OPTION["replan_every"])
        n = self.samples
        if n is not None and n > 1 and self.mode not in SAMPLING_MODES:
            raise ConfigError(f"{n} samples need the coherent or bid mode ({self.mode} "
                              "executes the one chunk it draws)", key=OPTION["samples"])
        if n is not None and n < 2 and self.mode in SAMPLING_MODES:
            raise ConfigError(f"{self.mode} chooses among at least 2 samples, got {n}",
                              key=OPTION["samples"])
        if self.decay != DEFAULT_DECAY and self.mode not in SAMPLING_MODES:
            raise ConfigError(f"a decay weighs coherence, which coherent and bid use, not "
                              f"{self.mode}", key=OPTION["decay"])
        if self.ensemble_k != DEFAULT_ENSEMBLE_K and self.mode != "ensemble":
            raise ConfigError(f"k weighs ensembled predictions, which ensemble uses, not "
                              f"{self.mode}", key=OPTION["ensemble_k"])
        if self.mode == "bid" and not self.weak:
            raise ConfigError("bid contrasts against a weaker policy: give --weak "
                              "CHECKPOINT[@SOLVER-STEPS] (e.g. train@euler-1)", key=OPTION["weak"])
        if self.weak and self.mode != "bid":
            raise ConfigError(f"a weaker policy is used by --execution bid only, not {self.mode}",
                              key=OPTION["weak"])

    @property
    def label(self) -> str:
        """As tables name it: `receding K=8`, `ensemble K=1`, `coherent K=1 N=16`."""
        out = f"{self.mode} K={self.replan_every if self.replan_every else 'default'}"
        if self.samples and self.samples > 1:
            out += f" N={self.samples}"
        if self.mode in SAMPLING_MODES and self.decay != DEFAULT_DECAY:
            out += f" decay={self.decay:g}"
        if self.mode == "ensemble" and self.ensemble_k != DEFAULT_ENSEMBLE_K:
            out += f" k={self.ensemble_k:g}"
        return out

    def to_json(self) -> dict[str, Any]:
        return to_dict(self)

    @classmethod
    def from_json(cls, data: dict, source: str | None = None) -> "ExecutionSettings":
        return from_dict(cls, data, source=source)


def parse_spec(spec: str, weak: str | None = None) -> ExecutionSettings:
    """MODE[-K][xN] (receding-4, ensemble-1, coherent-1x16, bid-2x16) -> settings; ConfigError
    naming the spec when it is not one. `weak`: bid's weaker policy."""
    head, _, n = spec.partition("x")
    mode, _, k = head.partition("-")
    if mode not in MODES or (k and not k.isdigit()) or (n and not n.isdigit()):
        raise ConfigError(f"'{spec}' is not MODE[-K][xN] with MODE one of {', '.join(MODES)} "
                          "(e.g. receding-4, ensemble-1, coherent-1x16)", key="--candidate")
    return ExecutionSettings(mode, int(k) if k else None, int(n) if n else None,
                             weak=weak if mode == "bid" else None)


def candidates(n_action_steps: int, weak: str | None = None) -> list[ExecutionSettings]:
    """The executions `sefa choose-execution` tries by default: receding horizon replanning
    every 1, 2, 4 and n_action_steps steps, ACT's ensembling, 16 coherent samples every 1, 2
    and 4 steps, and with a weaker policy Bidirectional Decoding likewise."""
    periods = sorted({k for k in (1, 2, 4, n_action_steps) if k <= n_action_steps})
    few = [k for k in (1, 2, 4) if k <= n_action_steps]
    out = [ExecutionSettings("receding", k) for k in periods] + [ExecutionSettings("ensemble", 1)]
    out += [ExecutionSettings("coherent", k, DEFAULT_SAMPLES) for k in few]
    if weak:
        out += [ExecutionSettings("bid", k, DEFAULT_SAMPLES, weak=weak) for k in few]
    return [c.resolved(n_action_steps) for c in out]


def default_settings(n_action_steps: int) -> ExecutionSettings:
    """The field's execution: n_action_steps actions per prediction."""
    return ExecutionSettings().resolved(n_action_steps)


# ---- the selection math: pure functions on arrays

def ensemble_weights(n: int, k: float) -> np.ndarray:
    """Normalized weights of n predictions of one step, oldest first: exp(-k * i) / sum."""
    w = np.exp(-k * np.arange(n, dtype=np.float64))
    return w / w.sum()


def decay_weights(n: int, decay: float) -> np.ndarray:
    """decay^i for the n shared steps, i = 0 the step about to be executed, divided by their
    sum: the near steps count most."""
    w = decay ** np.arange(n, dtype=np.float64)
    return w / w.sum()


def coherence_cost(chunks: np.ndarray, prior: np.ndarray, decay: float) -> np.ndarray:
    """(N,) backward coherence of N chunks (N, T, Da) with the previous decision's plan for the
    same steps, prior (L, Da), L <= T: sum_i w_i ||chunk[i] - prior[i]||_2 over the L shared
    steps, w = decay_weights (the reference's `coherence_sampler`)."""
    n = len(prior)
    dist = np.linalg.norm(np.asarray(chunks, np.float64)[:, :n] - prior[None], axis=-1)
    return dist @ decay_weights(n, decay)


def chunk_distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N, M) distance of every chunk of a (N, T, Da) to every chunk of b (M, T, Da): the mean
    over the T steps of the per-step Euclidean norm."""
    diff = np.asarray(a, np.float64)[:, None] - np.asarray(b, np.float64)[None]
    return np.linalg.norm(diff, axis=-1).mean(axis=-1)


def contrast_cost(strong: np.ndarray, weak: np.ndarray | None) -> np.ndarray:
    """(N,) forward contrast of N >= 2 samples: the mean distance to the k = N // 2 nearest of
    the other samples minus the mean distance to the k nearest of the weaker policy's samples
    (none: the first term alone). Low: a chunk where the policy's samples agree, away from
    where the weaker policy's go (the reference's `bidirectional_sampler`)."""
    n = len(strong)
    k = max(n // 2, 1)
    own = np.sort(chunk_distances(strong, strong), axis=1)[:, 1:k + 1]  # column 0: itself
    cost = own.mean(axis=1)
    if weak is not None:
        cost = cost - np.sort(chunk_distances(strong, weak), axis=1)[:, :k].mean(axis=1)
    return cost


def bid_choice(strong: np.ndarray, weak: np.ndarray | None, prior: np.ndarray | None,
               decay: float) -> int:
    """The index of Bidirectional Decoding's choice among N chunks (N, T, Da): with a prior,
    the N // 3 (at least 2) most coherent of each policy's samples are kept, and the one with
    the least coherence + contrast among the kept strong ones wins; without one (an episode's
    first decision), contrast alone over all of them."""
    idx = np.arange(len(strong))
    coherence = np.zeros(len(strong))
    if prior is not None and len(prior):
        keep = max(len(strong) // CONTRAST_KEEP, 2)
        coherence = coherence_cost(strong, prior, decay)
        idx = np.argsort(coherence, kind="stable")[:keep]
        if weak is not None:
            weak = weak[np.argsort(coherence_cost(weak, prior, decay), kind="stable")[:keep]]
    cost = coherence[idx] + contrast_cost(strong[idx], weak)
    return int(idx[int(np.argmin(cost))])


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


# ---- the executor

# (one observation with a batch axis: per key (1, To, ...), noise (n, horizon, Da) float32,
# the episode's torch.Generator) -> its n chunks (n, horizon, Da) in action units; a sampler
# encodes the observation once for the n noises (Policy.predict_action does)
ChunkSampler = Callable[[dict[str, np.ndarray], np.ndarray, Any], np.ndarray]


@dataclass(frozen=True)
class ChunkShape:
    """What the executor needs to know of a policy's chunks."""
    n_obs_steps: int
    n_action_steps: int
    horizon: int
    action_dim: int

    @property
    def start(self) -> int:
        return self.n_obs_steps - 1  # Diffusion Policy: act from the current (last observed) frame

    @classmethod
    def of(cls, meta: dict) -> "ChunkShape":
        """From an export's metadata.json (or a served checkpoint's)."""
        return cls(meta["n_obs_steps"], meta["n_action_steps"], meta["horizon"], meta["action_dim"])


class Executor:
    """One episode at a time: frames in, one action per control step out (the module docstring
    says how). `replanned` and `count` describe the last step: whether it predicted, and the
    actions left in the plan (ensemble: the predictions averaged)."""

    def __init__(self, settings: ExecutionSettings, sample: ChunkSampler, shape: ChunkShape, *,
                 seed: int = 0, weak: ChunkSampler | None = None):
        self.settings = settings.resolved(shape.n_action_steps)
        if self.settings.mode == "bid" and weak is None:
            raise ValueError("bid needs the weaker policy's sampler (weak)")
        import torch  # here: the settings and the math load without torch (sefa.yaml's reader)

        self.sample, self.weak, self.shape = sample, weak, shape
        self.generator = torch.Generator()
        self.ensembler = Ensembler(self.settings.ensemble_k)
        # the wall time of every decision this executor made (every episode): what a robot
        # waits for at a replanning step, as rollouts report it beside the score
        self.decision_seconds: list[float] = []
        self.seed: int | None = None  # the last episode's, named when its policy fails
        self.reset(seed)

    @classmethod
    def for_policy(cls, policy, settings: ExecutionSettings | None = None, *, seed: int = 0,
                   solver: str | None = None, steps: int | None = None, weak=None,
                   nfe: list[int] | None = None) -> "Executor":
        """A loaded `Policy` (and for bid the weaker one, a (Policy, solver, steps) triple)."""
        shape = policy_shape(policy)
        settings = settings or default_settings(shape.n_action_steps)
        weak_fn = None if weak is None else policy_sampler(*weak)
        return cls(settings, policy_sampler(policy, solver, steps, nfe), shape, seed=seed,
                   weak=weak_fn)

    @classmethod
    def load(cls, checkpoint: str | Path, settings: ExecutionSettings | None = None, *,
             device: str = "auto", seed: int = 0, solver: str | None = None,
             steps: int | None = None) -> "Executor":
        """A checkpoint's executor: `settings`, else the execution chosen for it (sefa
        choose-execution), else receding horizon over n_action_steps. (bid needs the weaker
        policy: `for_policy(..., weak=(Policy, solver, steps))`.)"""
        from sefa_model.policy.artifact import Policy

        settings, _, _ = resolve_execution(checkpoint, settings, solver, steps)
        if settings.mode == "bid":
            raise ConfigError(f"{settings.label} needs the weaker policy loaded: use "
                              "Executor.for_policy(policy, settings, weak=(Policy, solver, "
                              "steps))", key=OPTION["weak"])
        return cls.for_policy(Policy.load(checkpoint, device=device), settings, seed=seed,
                              solver=solver, steps=steps)

    def reset(self, seed: int | None = None) -> None:
        """A new episode: no history, no plan; the noise generator seeded again when a seed is
        given (else it goes on)."""
        if seed is not None:
            self.generator.manual_seed(seed)
            self.seed = seed
        self.history: collections.deque = collections.deque(maxlen=self.shape.n_obs_steps)
        self.t, self.plan, self.plan_t = 0, None, 0
        self.ensembler.clear()
        self.replanned, self.count, self.decisions = False, 0, 0

    @property
    def steps_to_decision(self) -> int:
        """How many `action` calls from now the next prediction is (0: the next call predicts);
        a simulator that renders frames only when a decision will see them reads it."""
        if self.plan is None:
            return 0
        return max(self.plan_t + self.settings.replan_every - self.t, 0)

    def observation(self) -> dict[str, np.ndarray]:
        """The (To, ...) history per key the next decision sees: the keys of the episode's
        first frame."""
        keys = self.keys
        missing = [k for f in self.history for k in keys if k not in f]
        if missing:
            raise SefaInputError(f"observation '{missing[0]}' is missing from a frame the policy "
                                 "sees (every frame of the last n_obs_steps needs every key)",
                                 key=missing[0])
        return {k: np.stack([np.asarray(f[k]) for f in self.history]) for k in keys}

    def action(self, frame: dict[str, np.ndarray], noise: np.ndarray | None = None) -> np.ndarray:
        """The action (Da,) float32 to execute now, given the newest frame per key. `noise`
        (samples, horizon, Da) replaces the drawn noise when this step predicts."""
        if not self.history:  # a new episode: the first frame stands in for the past
            self.history.extend([frame] * self.shape.n_obs_steps)
            self.keys = list(frame)
        else:
            self.history.append(frame)
        self.replanned = self.steps_to_decision == 0
        if self.replanned:
            self._decide(noise)
        if self.settings.mode == "ensemble":
            action, self.count = self.ensembler.action(self.t)
        else:
            i = self.t - self.plan_t
            action = np.asarray(self.plan[self.shape.start + i], np.float32)
            self.count = self.settings.replan_every - i - 1
        self.t += 1
        return action

    def _draw(self, n: int, noise: np.ndarray | None) -> np.ndarray:
        import torch

        s = self.shape
        if noise is None:  # as Policy.predict_action draws it: the same numbers for n = 1
            return torch.randn((n, s.horizon, s.action_dim), generator=self.generator).numpy()
        noise = np.asarray(noise, np.float32)
        return noise[None] if noise.ndim == 2 else noise

    def _finite(self, chunks, who: str = "the policy") -> np.ndarray:
        """Chunks as an array, refused when any value is NaN or Inf: a simulator would score
        them (Push-T reads a NaN target as reward 0) and a robot would move to them."""
        chunks = np.asarray(chunks)
        if not np.isfinite(chunks).all():
            episode = f" of the episode seeded {self.seed}" if self.seed is not None else ""
            raise NonFiniteError(f"{who} predicted a non-finite action chunk (NaN or Inf) at "
                                 f"step {self.t}{episode}: nothing of it is executed")
        return chunks

    def _decide(self, noise: np.ndarray | None) -> None:
        started = time.perf_counter()
        st, s = self.settings, self.shape
        obs = self.observation()
        n = st.samples
        batch = {k: v[None] for k, v in obs.items()}  # one observation for the n noises
        chunks = self._finite(self.sample(batch, self._draw(n, noise), self.generator))
        self.decisions += 1
        choice = 0
        if st.mode in SAMPLING_MODES:
            # the previous plan's steps from now on, against each sample's from now on
            prior = None if self.plan is None else self.plan[s.start + self.t - self.plan_t:]
            future = chunks[:, s.start:]
            if st.mode == "coherent":
                if prior is not None and len(prior):
                    choice = int(np.argmin(coherence_cost(future, prior, st.decay)))
            else:
                weak = self._finite(self.weak(batch, self._draw(n, None), self.generator),
                                    "the weaker policy (--weak)")
                choice = bid_choice(future, weak[:, s.start:], prior, st.decay)
        self.plan, self.plan_t = np.asarray(chunks[choice], np.float64), self.t
        if st.mode == "ensemble":  # the steps a chunk is executed on (ACT: the whole chunk)
            self.ensembler.add(self.t, self.plan[s.start:s.start + s.n_action_steps])
        self.decision_seconds.append(time.perf_counter() - started)


def policy_shape(policy) -> ChunkShape:
    p = policy.cfg.policy
    return ChunkShape(p.n_obs_steps, p.n_action_steps, p.horizon,
                      policy.cfg.shape_meta.action.shape[-1])


def policy_sampler(policy, solver: str | None = None, steps: int | None = None,
                   nfe: list[int] | None = None) -> ChunkSampler:
    """A loaded `Policy` at a sampler setting (default: its own) as the executor calls it;
    each call's network evaluations are appended to `nfe` when given."""
    import torch

    from sefa_model.policy.sampling import resolve_solver

    solver, steps = resolve_solver(policy.cfg, solver, steps)

    def sample(obs: dict[str, np.ndarray], noise: np.ndarray, generator: torch.Generator):
        out = policy.predict_action(obs, solver=solver, steps=steps,
                                    noise=torch.from_numpy(noise), generator=generator)
        if nfe is not None:
            nfe.append(int(out.nfe))
        return out.action_pred.cpu().numpy()
    return sample


# ---- the execution chosen for a policy, kept with it

RECORD_FORMAT = 1


def save_choice(checkpoint: str | Path, settings: ExecutionSettings, solver: str,
                details: dict[str, Any]) -> Path:
    """Record `settings` as the execution of the checkpoint at sampler setting `solver` (a
    label such as euler-1), with how it was chosen (`details`); tied to the checkpoint's
    weights by its digest, so a retrained checkpoint does not inherit it."""
    from sefa_data import atomic
    from sefa_model.policy.checkpoint import (EXECUTION_FILE, checkpoint_digest,
                                             resolve_checkpoint)

    ckpt = resolve_checkpoint(checkpoint)
    record = {"sefa_execution": RECORD_FORMAT, "execution": settings.to_json(),
              "label": settings.label, "solver": solver,
              "checkpoint_digest": checkpoint_digest(ckpt), **details}
    path = ckpt / EXECUTION_FILE
    atomic.write_json(path, record)
    return path


def load_choice(checkpoint: str | Path, solver: str | None = None) -> ExecutionSettings | None:
    """The execution recorded for this checkpoint (at sampler setting `solver`, when given), or
    None: no record, one for another sampler setting, or one written for other weights. A
    record that cannot be read is an error naming the file."""
    from sefa_model.policy.checkpoint import (EXECUTION_FILE, checkpoint_digest,
                                             resolve_checkpoint)

    ckpt = resolve_checkpoint(checkpoint)
    path = ckpt / EXECUTION_FILE
    if not path.is_file():
        return None
    try:
        record = json.loads(path.read_text())
        ok = isinstance(record, dict) and record.get("sefa_execution") == RECORD_FORMAT
    except (OSError, ValueError, UnicodeDecodeError) as e:
        raise SefaInputError(f"unreadable ({e})", file=str(path)) from None
    if not ok:
        raise SefaInputError(f"not a sefa execution record of format {RECORD_FORMAT}", file=str(path))
    if record.get("checkpoint_digest") != checkpoint_digest(ckpt):
        return None
    if solver is not None and record.get("solver") != solver:
        return None
    return ExecutionSettings.from_json(record.get("execution"), source=str(path))


def resolve_execution(checkpoint: str | Path, asked: ExecutionSettings | None,
                      solver: str | None = None, steps: int | None = None,
                      fallback: ExecutionSettings | None = None
                      ) -> tuple[ExecutionSettings, str, int]:
    """(the execution an evaluation of this checkpoint at this sampler setting runs, resolved;
    where it came from; the policy's n_action_steps): `asked` ("given"), else `fallback` (a
    workspace's sefa.yaml: "sefa.yaml"), else the one chosen for the policy ("chosen"), else
    receding horizon over n_action_steps ("default"). Reads the checkpoint's config, not its
    weights."""
    from sefa_model.config import saved_train_config
    from sefa_model.policy.checkpoint import read_json, resolve_checkpoint
    from sefa_model.policy.sampling import solver_label

    ckpt = resolve_checkpoint(checkpoint)
    cfg = saved_train_config(read_json(ckpt / "config.json")["train_config"],
                             source=str(ckpt / "config.json"))
    n = cfg.policy.n_action_steps
    if asked is not None:
        return asked.resolved(n), "given", n
    if fallback is not None:
        return fallback.resolved(n, source="sefa.yaml"), "sefa.yaml", n
    chosen = load_choice(ckpt, solver_label(cfg, solver, steps))
    if chosen is not None:
        return chosen.resolved(n), "chosen", n
    return default_settings(n), "default", n


def read_record(checkpoint: str | Path) -> dict | None:
    """The whole record (how it was chosen included), or None."""
    from sefa_model.policy.checkpoint import EXECUTION_FILE, resolve_checkpoint

    path = resolve_checkpoint(checkpoint) / EXECUTION_FILE
    return json.loads(path.read_text()) if path.is_file() else None
