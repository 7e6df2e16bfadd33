"""What one decision of a served policy costs on this machine, measured when `sefa serve`
starts, and which executions that leaves within the robot's control period.

The server times its backend on a made-up observation of the metadata's shapes (zeros, mid-grey
images): the cost of the network and sampler is the same for any observation, except an adaptive
solver's, whose steps vary with it. The executions are judged as `sefa bench latency` judges
them (sefa_model/eval/latency.py): the worst step of a synchronous controller is one whole
decision, so an execution fits when a decision's p99 stays within the period.
"""

from __future__ import annotations

import numpy as np

from sefa_model.eval.latency import (FIT_PERCENTILE, execution_cost, fit_summary,
                                     named_percentiles_ms, single_chunk_costs, time_calls)

CALLS, WARMUP, MAX_SECONDS = 10, 2, 3.0  # a slow sampler stops after 3 s (at least 10 calls)


def example_request(meta: dict, n: int = 1) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """(obs, noise) of the metadata's shapes, batch n: zeros, images mid-grey."""
    obs = {k: np.full((n, *spec["shape"]), 128 if spec["dtype"] == "uint8" else 0,
                      dtype=spec["dtype"]) for k, spec in meta["obs"].items()}
    noise = np.random.default_rng(0).standard_normal((n, *meta["noise"]["shape"]),
                                                     dtype=np.float32)
    return obs, noise


def served_decisions(backend, execution, fps: float | None, weak=None) -> dict:
    """p50 / p99 ms of one decision drawing one chunk and, for an execution drawing N chunks a
    decision, one of N (and the weaker policy's, for bid); each execution's cost per step at
    `fps`; and the lines that say which fit."""
    n = execution.samples or 1
    calls = {1: _call(backend, 1)}
    if n > 1:
        calls[n] = _call(backend, n)
    if weak is not None:
        calls["weak"] = _call(weak, n)
    times = time_calls(calls, warmup=WARMUP, calls=CALLS, max_seconds=MAX_SECONDS,
                       sync=lambda: None)
    p = {k: named_percentiles_ms(v) for k, v in times.items()}
    one_p50, one_worst = p[1]["p50_ms"], p[1][FIT_PERCENTILE]
    rows = single_chunk_costs(backend.metadata["n_action_steps"], one_p50, one_worst, fps)
    if n > 1 or weak is not None:  # the served execution itself, at its N (and the weak call)
        extra = p["weak"] if weak is not None else {"p50_ms": 0.0, FIT_PERCENTILE: 0.0}
        rows.append(execution_cost(execution, p[n]["p50_ms"] + extra["p50_ms"], fps,
                                   p[n][FIT_PERCENTILE] + extra[FIT_PERCENTILE]))
    served = next((r for r in rows if r["execution"] == execution.label), None)
    executions = [{"target": "this policy", **r} for r in rows]
    return {"decision_ms": one_p50, "worst_ms": one_worst, "fps": fps, "served": served,
            "executions": executions, "lines": fit_summary(executions, fps)}


def _call(backend, n: int):
    """One decision of n chunks as the server's executor asks for it: one observation, n noises."""
    obs, _ = example_request(backend.metadata, 1)
    _, noise = example_request(backend.metadata, n)
    return lambda: backend(obs, noise)
