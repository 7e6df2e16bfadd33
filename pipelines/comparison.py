"""The comparison SeFA's claim is about: each policy's closed-loop result minus a reference's
(the teacher: the base flow at its own solver), paired over the seeds both evaluations ran, with
its standard error, beside the ratio of their decision latencies (`sefa compare`, and the table
under `sefa results`).

Pairing by seed cancels the seeds' difficulty: the difference of two policies on the same 50
scenes has a far smaller standard error than the difference of their means. Two evaluations
pair when they ran in the same simulator with the same episode length; the seeds are matched
by value (Meta-World: by task and seed), so evaluations of 50 and of 200 seeds from the same
start pair over the first 50. A seed's value is its score where the simulator gives one
(Push-T), else its success (0 or 1).

The latencies are those the rollouts measured (each decision's wall time in the loop, the p50;
`decision_ms` in the eval log): a ratio is given only for two evaluations timed with the same
number of torch threads. Evaluations kept before rollouts timed their decisions have none;
`sefa bench latency A B` measures both in one process.
"""

from __future__ import annotations

import math
from typing import Any

MIN_PAIRED = 2  # a standard error needs two differences


def seed_values(result: dict[str, Any]) -> dict[tuple, float]:
    """(task, seed) -> the episode's score, else its success, from a rollout log."""
    out = {}
    for p in result.get("per_seed") or []:
        value = p.get("score", p.get("success"))
        if value is not None:
            out[(p.get("task"), int(p["seed"]))] = float(value)
    return out


def paired_difference(a: dict[tuple, float], b: dict[tuple, float]
                      ) -> tuple[float, float | None, int]:
    """(mean of a - b over the keys both hold, its standard error (None below two pairs),
    the number of pairs); the sample standard deviation (ddof 1) over the square root of n."""
    keys = sorted(set(a) & set(b), key=lambda k: (str(k[0]), k[1]))
    diffs = [a[k] - b[k] for k in keys]
    n = len(diffs)
    if n == 0:
        return math.nan, None, 0
    mean = sum(diffs) / n
    if n < MIN_PAIRED:
        return mean, None, n
    var = sum((d - mean) ** 2 for d in diffs) / (n - 1)
    return mean, math.sqrt(var / n), n


def _rollouts(rows: list[dict]) -> list[dict]:
    return [r for r in rows if r.get("mode") != "offline" and r["result"].get("per_seed")]


def _name(r: dict) -> str:
    return f"{r['checkpoint']}@{r['result'].get('solver') or '-'}"


def _matches(r: dict, names: set[str], solver: str) -> bool:
    """Whether evaluation `r` is of a checkpoint called one of `names` (as it was given, or
    the run folder it resolved to), at `solver` when one is given."""
    res = r["result"]
    named = bool(names & {r["checkpoint"], r.get("checkpoint_run")}) or any(
        (r.get("checkpoint_run") or "").startswith(n.rstrip("/") + "/") for n in names)
    return named and (not solver or (res.get("solver") or "") == solver)


def reference_of(group: list[dict], against: str | None, aliases: tuple[str, ...] = ()
                 ) -> dict | None:
    """The reference among one simulator's evaluations: the one `against` names (CHECKPOINT
    or CHECKPOINT@SOLVER; `aliases`: the run folder the checkpoint resolves to; the newest of
    several), else the base flow's evaluation with the most network evaluations a chunk (its
    accurate solve, the teacher), else None."""
    if against is not None:
        path, _, solver = against.partition("@")
        named = [r for r in group if _matches(r, {path, *aliases}, solver)]
        return max(named, key=lambda r: r.get("created", "")) if named else None
    base = [r for r in group if r["result"].get("kind") == "base_flow"]
    if not base:
        return None
    return max(base, key=lambda r: (r["result"].get("nfe") or 0, r.get("created", "")))


def latency_ratio(policy: dict, reference: dict) -> tuple[float | None, str | None]:
    """(policy p50 / reference p50, None), or (None, why not)."""
    a, b = policy.get("decision_ms"), reference.get("decision_ms")
    if not a or not b:
        return None, "not timed (an evaluation kept before rollouts timed their decisions)"
    if a.get("threads") != b.get("threads"):
        return None, (f"timed with {a.get('threads')} and {b.get('threads')} torch threads: "
                      "not comparable")
    return a["p50_ms"] / b["p50_ms"], None


def comparisons(rows: list[dict], against: str | None = None, aliases: tuple[str, ...] = ()
                ) -> list[dict]:
    """Per simulator (and episode length), every rollout evaluation against the reference:
    the paired difference ± SE over the seeds both ran, both scores on those seeds, the
    decision latencies and their ratio. `rows`: `all_results`' records; `against`, `aliases`:
    as `reference_of` takes them."""
    groups: dict[tuple, list[dict]] = {}
    for r in _rollouts(rows):
        groups.setdefault((r["mode"], r["result"].get("max_steps")), []).append(r)
    out = []
    for (env, max_steps), group in groups.items():
        ref = reference_of(group, against, aliases)
        if ref is None:
            continue
        base = seed_values(ref["result"])
        for r in group:
            if r is ref:
                continue
            values = seed_values(r["result"])
            diff, se, n = paired_difference(values, base)
            if n == 0:
                continue
            common = set(values) & set(base)
            ratio, why = latency_ratio(r["result"], ref["result"])
            out.append({
                "env": env, "max_steps": max_steps, "policy": _name(r), "kind": r["result"].get("kind"),
                "execution": r["result"].get("execution_label"), "folder": r["folder"],
                "reference": _name(ref), "reference_folder": ref["folder"], "paired_seeds": n,
                "score": sum(values[k] for k in common) / n,
                "reference_score": sum(base[k] for k in common) / n,
                "difference": diff, "difference_se": se,
                "decision_ms": r["result"].get("decision_ms"),
                "reference_decision_ms": ref["result"].get("decision_ms"),
                "latency_ratio": ratio, "latency_note": why})
    return out


def workspace_comparisons(workspace, against: str | None = None) -> list[dict]:
    """`comparisons` of every evaluation kept in the workspace; `against`'s checkpoint also
    matched by the run folder it resolves to there (`train` is runs/train/<id>)."""
    import os
    from pathlib import Path

    from sefa_pipelines.evals import all_results, label

    aliases: tuple[str, ...] = ()
    if against is not None:
        path = Path(workspace) / against.partition("@")[0]
        if path.exists():
            aliases = (label(Path(workspace), Path(os.path.realpath(path))),)
    return comparisons(all_results(Path(workspace)), against, aliases)
