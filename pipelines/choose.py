"""`sefa choose-execution`: try the executions that fit a latency budget on validation seeds,
keep the best with the policy.

    choose(workspace, checkpoint, ChooseRequest("pusht"), device="cpu", log=print)

1. The candidates (`sefa_model.policy.execution.candidates`, or --candidates) and the time of
   one of their decisions on this machine: one batched call of N samples for one observation
   (`decision_times`, p99 as everywhere a period is judged: FIT_PERCENTILE; bid adds the
   weaker policy's N samples). A candidate whose decision does not fit the budget (default:
   the task's control period, 1000 / fps ms, so that a controller predicting synchronously
   keeps 99 % of its steps on time) is not tried.
2. Each candidate that fits is rolled out on the validation seeds (from VALIDATION_START_SEED;
   every test seed `sefa eval` uses lies in TEST_SEEDS, and a validation range reaching into it
   is refused), each result cached in WORKSPACE/evals/ like any `sefa eval`, so an interrupted
   choice continues where it stopped.
3. The best mean score wins (ties: the cheaper per control step), but only when it beats the
   field's default, n_action_steps actions per prediction, by at least `min_gain_se` paired
   standard errors over the validation seeds; otherwise the default is kept (`pick`). On 50
   seeds a difference's standard error is several points: on Push-T the best of ten on
   validation (ACT's ensembling, +0.014 ± 0.040) was 0.039 ± 0.016 below the default on 500
   test seeds. When the default is kept over a gain, the reason says how many validation
   seeds would show that gain at the rule. The choice is recorded with the policy
   (`execution.json` in its checkpoint, `save_choice`), with every candidate's validation score
   and latency, the rule and why it chose, and the cost of choosing. From then on `sefa eval`,
   `sefa serve`, `sefa export` (metadata.json) and the LeRobot integration run it by default.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable

import numpy as np

from sefa_data.errors import SefaInputError

# `sefa eval`'s test seeds come from here (Diffusion Policy's 100000 on); the chooser never
# rolls out a seed in this range
TEST_SEEDS = range(100_000, 200_000)
VALIDATION_START_SEED = 200_000
Log = Callable[[str], None]


@dataclass(frozen=True)
class ChooseRequest:
    env: str
    n_val: int = 50
    val_start_seed: int = VALIDATION_START_SEED
    max_steps: int | None = None
    solver: str | None = None
    steps: int | None = None
    budget_ms: float | None = None  # None: the control period
    fps: float | None = None  # None: the policy's store's
    candidates: tuple[str, ...] = ()  # MODE-K[xN] specs; empty: the default grid
    weak: str | None = None  # bid's weaker policy; without one bid is not tried
    min_gain_se: float = 2.0  # leave the default only this many paired standard errors above it


def check_validation_seeds(start: int, n: int) -> None:
    """A validation range must not reach into the test seeds: one line naming the option."""
    if start < TEST_SEEDS.stop and start + n > TEST_SEEDS.start:
        raise SefaInputError(
            f"validation seeds {start}..{start + n - 1} overlap the test seeds "
            f"({TEST_SEEDS.start}..{TEST_SEEDS.stop - 1}, what `sefa eval` reports on); start at "
            f"{TEST_SEEDS.stop} or below {TEST_SEEDS.start - n + 1}", key="--val-start-seed")


def control_rate(policy, fps: float | None) -> float:
    if fps is not None:
        return fps
    from sefa_deploy.metadata import find_fps

    found, where = find_fps(policy)
    if found is None:
        raise SefaInputError(f"the control rate is unknown ({where})", key="--fps")
    return found


def latencies(policy, cands, req: ChooseRequest, device: str, store: Path | None) -> dict:
    """Each candidate's decision time (ms, at FIT_PERCENTILE): its N samples, plus the weaker
    policy's."""
    from sefa_model.eval.latency import FIT_PERCENTILE, decision_times, parse_target
    from sefa_model.policy.artifact import Policy

    sizes = tuple(sorted({c.samples for c in cands}))
    own = {r["samples"]: r[FIT_PERCENTILE] for r in decision_times(
        policy, sizes, solver=req.solver, steps=req.steps, store=store)}
    weak = {}
    if any(c.mode == "bid" for c in cands):
        path, solver, steps = parse_target(req.weak)
        weak_policy = Policy.load(path, device=device)
        bid_sizes = tuple(sorted({c.samples for c in cands if c.mode == "bid"}))
        weak = {r["samples"]: r[FIT_PERCENTILE] for r in decision_times(
            weak_policy, bid_sizes, solver=solver, steps=steps, store=store)}
    return {c.label: own[c.samples] + (weak[c.samples] if c.mode == "bid" else 0.0)
            for c in cands}


def choose(workspace: Path, checkpoint: Path, req: ChooseRequest, *, device: str, log: Log,
           force: bool = False) -> dict[str, Any]:
    from sefa_model.eval.latency import execution_cost
    from sefa_model.policy.artifact import Policy
    from sefa_model.policy.execution import candidates, parse_spec, save_choice
    from sefa_model.policy.sampling import solver_label
    from sefa_pipelines.evals import EvalRequest, evaluate
    from sefa_pipelines.stages import STORE

    check_validation_seeds(req.val_start_seed, req.n_val)
    started = time.monotonic()
    policy = Policy.load(checkpoint, device=device)
    n = policy.cfg.policy.n_action_steps
    weak = None if req.weak is None else req.weak
    cands = ([parse_spec(s, weak).resolved(n) for s in req.candidates] if req.candidates
             else candidates(n, weak))
    fps = control_rate(policy, req.fps)
    budget = req.budget_ms if req.budget_ms is not None else 1000.0 / fps
    store = workspace / STORE if (workspace / STORE).exists() else None
    decision = latencies(policy, cands, req, device, store)
    rows = []
    for c in cands:
        cost = execution_cost(c, decision[c.label], fps)
        rows.append({**cost, "settings": c.to_json(), "label": c.label,
                     "within_budget": decision[c.label] <= budget})
    tried = [(c, r) for c, r in zip(cands, rows) if r["within_budget"]]
    if not tried:
        fastest = min(rows, key=lambda r: r["decision_ms"])
        raise SefaInputError(f"no execution fits the budget of {budget:.3g} ms a decision (the "
                             f"fastest, {fastest['label']}, takes {fastest['decision_ms']:.3g} ms "
                             "on this machine); raise --budget-ms", key="--budget-ms")
    log(f"{len(tried)} of {len(cands)} executions fit {budget:.3g} ms a decision; rolling each "
        f"out on validation seeds {req.val_start_seed}..{req.val_start_seed + req.n_val - 1}")
    episodes = 0
    for c, row in tried:
        request = EvalRequest(req.env, req.n_val, req.val_start_seed, req.max_steps, req.solver,
                              req.steps, execution=c)
        record = evaluate(workspace, [checkpoint], request, device=device, force=force,
                          out=None, is_main=True, log=log)[0]
        per_seed = sorted(record["result"]["per_seed"], key=lambda p: (p.get("task", ""), p["seed"]))
        row["scores"] = [float(p.get("score", p["success"])) for p in per_seed]
        row["mean_score"] = float(np.mean(row["scores"]))
        row["eval"] = record["key"]
        episodes += 0 if record["cached"] else len(per_seed)
    default = f"receding K={n}"
    paired_with_default(rows, default)
    chosen, why = pick([r for _, r in tried], default, req.min_gain_se)
    best_c = next(c for c, r in tried if r["label"] == chosen)
    summary = summarize(rows, chosen, why, budget, fps, req, started, episodes)
    label = solver_label(policy.cfg, req.solver, req.steps)
    summary["record"] = str(save_choice(checkpoint, best_c, label, summary))
    return summary


def paired_with_default(rows: list[dict], default: str) -> None:
    """Each rolled-out candidate's mean score minus the default's, paired over the validation
    seeds, and its standard error (`minus_default`, `minus_default_se`; None from one seed)."""
    from sefa_pipelines.comparison import paired_difference

    def by_seed(scores: list[float]) -> dict[tuple, float]:
        return {("", i): s for i, s in enumerate(scores)}  # the same validation seeds, in order

    base = next((r["scores"] for r in rows if r["label"] == default and "scores" in r), None)
    for r in rows:
        if base is not None and "scores" in r and r["label"] != default:
            r["minus_default"], r["minus_default_se"], _ = paired_difference(
                by_seed(r["scores"]), by_seed(base))


def pick(rows: list[dict], default: str, min_gain_se: float) -> tuple[str, str]:
    """The label chosen among rolled-out rows (`mean_score`, `mean_step_ms`, and against the
    default `minus_default`, `minus_default_se`) and why: the best mean (ties: the cheaper per
    step), unless the default was rolled out too and the best is not `min_gain_se` standard
    errors above it (a gain with no spread at all, every seed the same, counts)."""
    best = min(rows, key=lambda r: (-r["mean_score"], r["mean_step_ms"]))
    if best["label"] == default:
        return default, "the best on the validation seeds"
    if not any(r["label"] == default for r in rows):
        return best["label"], f"the best on the validation seeds ({default} was not tried)"
    gain, se = best["minus_default"], best.get("minus_default_se") or 0.0
    if gain > 0 and gain >= min_gain_se * se:
        return best["label"], (f"the best on the validation seeds, {gain:+.3f} ± {se:.3f} over "
                               f"{default}")
    why = (f"the default: the best on the validation seeds, {best['label']}, is {gain:+.3f} ± "
           f"{se:.3f} over it, less than {min_gain_se:g} standard errors")
    if gain > 0 and se > 0 and "scores" in best:
        # the standard error falls as 1/sqrt(seeds): the seeds at which this gain would reach
        # the rule, a floor (the best of several is likely to fall back on new seeds)
        n = math.ceil(len(best["scores"]) * (min_gain_se * se / gain) ** 2)
        why += f"; more validation seeds would decide it (at this gain, --n-val {n} or more)"
    return default, why


def summarize(rows: list[dict], chosen: str, why: str, budget: float, fps: float,
              req: ChooseRequest, started: float, episodes: int) -> dict[str, Any]:
    """What the record keeps of how the choice was made: the candidates, each one's validation
    score (and against the field's default, paired), the rule, the budget, the seeds, the
    cost."""
    for r in rows:
        r.pop("scores", None)
    return {"chosen": chosen, "why": why, "min_gain_se": req.min_gain_se, "env": req.env,
            "fps": fps, "budget_ms": budget,
            "validation_seeds": [req.val_start_seed, req.val_start_seed + req.n_val - 1],
            "candidates": rows, "seconds": round(time.monotonic() - started, 1),
            "episodes_run": episodes}


def with_weak(req: ChooseRequest, workspace: Path) -> ChooseRequest:
    """bid's weaker policy path, a relative checkpoint looked for in the workspace first."""
    if req.weak is None:
        return req
    path, at, setting = req.weak.partition("@")
    if not Path(path).is_absolute() and (workspace / path).exists():
        path = str(workspace / path)
    return replace(req, weak=path + at + setting)
