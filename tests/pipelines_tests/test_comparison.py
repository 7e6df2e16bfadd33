"""`sefa compare` and the table under `sefa results`: each closed-loop evaluation minus the
teacher's, paired over the seeds both ran, ± its standard error, with the latency ratio of the
decisions the rollouts timed; checked against benchmarks/paired_evals.py on the same logs
(real Push-T rollouts of the deployment tests' tiny base flow and one-step student)."""

from __future__ import annotations

import json
import math
import shutil

import pytest

from benchmark_module import load
from cli_inprocess import run_cli
from sefa_pipelines.comparison import paired_difference, reference_of, seed_values


def test_paired_difference_is_the_mean_difference_over_common_seeds_and_its_se():
    a = {(None, 1): 1.0, (None, 2): 0.5, (None, 3): 0.0, (None, 9): 1.0}
    b = {(None, 1): 0.5, (None, 2): 0.5, (None, 3): 0.5}  # seed 9: not in b, not paired
    diff, se, n = paired_difference(a, b)
    # differences 0.5, 0, -0.5: mean 0, sample sd 0.5, se 0.5 / sqrt(3)
    assert (n, diff) == (3, 0.0) and se == pytest.approx(0.5 / math.sqrt(3))
    assert paired_difference(a, {(None, 1): 0.0})[1:] == (None, 1)  # one pair: no SE
    assert paired_difference(a, {})[2] == 0
    # Meta-World pairs by (task, seed): the same seed of two tasks is two episodes
    mw = seed_values({"per_seed": [{"task": "reach", "seed": 5, "success": True},
                                   {"task": "push", "seed": 5, "success": False}]})
    assert mw == {("reach", 5): 1.0, ("push", 5): 0.0}


def test_the_default_reference_is_the_base_flows_most_accurate_solve():
    rows = [{"checkpoint": "train", "checkpoint_run": "runs/train/a", "created": "1",
             "result": {"kind": "base_flow", "nfe": 1, "solver": "euler-1"}},
            {"checkpoint": "train", "checkpoint_run": "runs/train/a", "created": "0",
             "result": {"kind": "base_flow", "nfe": 112.5, "solver": "rk45"}},
            {"checkpoint": "distill", "checkpoint_run": "runs/distill/b", "created": "2",
             "result": {"kind": "sefa_one_step", "nfe": 1, "solver": "euler-1"}}]
    assert reference_of(rows, None)["result"]["solver"] == "rk45"
    assert reference_of(rows, "train@euler-1")["result"]["nfe"] == 1
    assert reference_of(rows, "distill")["checkpoint"] == "distill"
    assert reference_of(rows, "runs/train/a@rk45")["result"]["nfe"] == 112.5  # its run folder
    assert reference_of(rows[2:], None) is None  # no base flow evaluated: no reference


@pytest.fixture(scope="module")
def evaluated(deploy_workspace, tmp_path_factory):
    """A workspace with the tiny base flow at Euler-4 on 6 test seeds and the one-step student
    on 4 of them (40 steps each), evaluated by `sefa eval --env pusht`."""
    pytest.importorskip("pymunk", reason="the sim extra is not installed")
    ws = tmp_path_factory.mktemp("compare")
    for name in ("flow", "distill"):
        shutil.copytree(deploy_workspace / name, ws / name)
    shutil.copytree(deploy_workspace / "dataset.zarr", ws / "dataset.zarr")
    for args in (["flow", "--solver", "euler", "--steps", "4", "--n-test", "6"],
                 ["distill", "--n-test", "4"]):
        r = run_cli("eval", *args, "--env", "pusht", "--max-steps", "40", "--threads", "1",
                    "--device", "cpu", "-w", ws)
        assert r.returncode == 0, r.stderr
    return ws


def test_compare_agrees_with_paired_evals_on_the_same_logs(evaluated):
    ws = evaluated
    r = run_cli("compare", "--json", "-w", ws)
    assert r.returncode == 0, r.stderr
    (row,) = json.loads(r.stdout)
    assert row["reference"].startswith("flow@euler") and row["policy"].startswith("distill")
    # benchmarks/paired_evals.py on the same eval_log.json files: the same difference and SE
    paired_evals = load("paired_evals")
    logs = paired_evals.evaluations(ws)
    # named by the run's folder, then its solver and execution
    (flow,) = [d for k, d in logs.items() if k.startswith("flow [")]
    (student,) = [d for k, d in logs.items() if k.startswith("distill [")]
    diff, se = load("reflow_rounds").paired(paired_evals.scores(student),
                                           paired_evals.scores(flow))
    assert row["paired_seeds"] == 4
    assert row["difference"] == pytest.approx(diff) and row["difference_se"] == pytest.approx(se)
    # the latency ratio: the p50 of the decisions each rollout timed, at the same threads
    assert student["decision_ms"]["threads"] == flow["decision_ms"]["threads"] == 1
    assert student["decision_ms"]["decisions"] == 4 * 5  # 40 steps / 8 a decision, 4 seeds
    assert row["latency_ratio"] == pytest.approx(student["decision_ms"]["p50_ms"]
                                                 / flow["decision_ms"]["p50_ms"])


def test_results_prints_the_comparison_under_its_list(evaluated):
    r = run_cli("results", "-w", evaluated)
    assert r.returncode == 0, r.stderr
    out = " ".join(r.stdout.split())
    assert "paired over the seeds both ran" in out and "difference ± SE" in out
    assert "latency ratio" in out and "decision p50" in out
    r = run_cli("compare", "--against", "nothing", "-w", evaluated)
    assert r.returncode == 0 and "no evaluation of nothing" in r.stdout
