"""The latency-budget study (benchmarks/latency_budget.py, issue 26): the study itself is not run
in CI, but its students are built here on a tiny base (the deployment tests' flow, trained in
seconds on the real Push-T data), and its report is checked on made-up scores."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def budget():
    from benchmark_module import load

    return load("latency_budget")


def test_students_of_every_k_with_and_without_alignment_from_a_lean_base(budget, deploy_workspace, tmp_path):
    from sefa_model.train import loop as training
    from sefa_model.data.couplings import aligned_attrs
    from sefa_model.policy.artifact import Policy

    ws = tmp_path / "ws"
    ws.mkdir()
    shutil.copytree(deploy_workspace / "dataset.zarr", ws / "dataset.zarr")
    base = tmp_path / "base"  # what a policy needs, as the GPU study copied its bases back
    shutil.copytree(deploy_workspace / "flow" / "checkpoints" / "latest", base)
    shutil.rmtree(base / "training_state")
    (base / "model.safetensors").unlink()

    students = budget.build_students(ws, base, [1, 2], eps=0.5, windows=32, samples=2, train_steps=3,
                                     threads=1)
    assert sorted(students) == ["reflow_k1", "reflow_k2", "reflowed_flow", "sefa_k1", "sefa_k2"]
    flow = json.loads((students.pop("reflowed_flow") / "checkpoints/latest/config.json").read_text())
    assert flow["train_config"]["flow"]["t_train"] == "uniform"
    for slug, run in students.items():
        flow = json.loads((run / "checkpoints/latest/config.json").read_text())["train_config"]["flow"]
        k = int(slug[-1])
        assert (flow["t_train"], flow["steps"], flow["solver"]) == (("start" if k == 1 else "grid"), k, "euler")
    attrs = aligned_attrs(ws / "budget" / "aligned_eps0.5.zarr")
    assert attrs["n"] == 64 and attrs["eps"] == 0.5
    obs = {"keypoint": np.zeros((2, 9, 2), np.float32) + 200, "state": np.zeros((2, 5), np.float32) + 250}
    assert Policy.load(students["sefa_k2"], device="cpu").predict_action(obs).nfe == 2

    # a second run reuses the couplings and every student
    def no_training(*a, **k):
        raise AssertionError("trained again")
    from sefa_model.sefa import reflow

    original, training.train = training.train, no_training
    made, reflow.generate_couplings = reflow.generate_couplings, no_training
    try:
        again = budget.build_students(ws, base, [1, 2], eps=0.5, windows=32, samples=2,
                                      train_steps=3, threads=1)
    finally:
        training.train, reflow.generate_couplings = original, made
    assert again == {**students, "reflowed_flow": ws / "budget" / "reflowed_flow"}


def made_up(budget, tmp_path):
    students = {f"{v}_k{k}": tmp_path / f"{v}_k{k}" for v in ("reflow", "sefa") for k in (1, 2, 4)}
    students["reflowed_flow"] = tmp_path / "reflowed"
    table = budget.rows(tmp_path / "base", tmp_path / "ddpm", students, [1, 2, 4], 0.05, 3000, 10,
                        2000, 0.12)
    score = {"base_rk45": 0.80, "base_euler1": 0.55, "reflow_k1": 0.70, "sefa_k1": 0.72,
             "sefa_k2": 0.79, "reflow_k2": 0.78, "ddim10": 0.78, "ddpm100": 0.81}
    p50 = {"base_rk45": 100.0, "ddpm100": 90.0, "ddim10": 9.5, "base_euler4": 3.5,
           "reflow_k4": 3.4, "sefa_k4": 3.4, "base_euler2": 1.9, "reflow_k2": 1.9, "sefa_k2": 2.0}
    timing = {}
    for r in table:
        s = score.get(r.slug, 0.6)
        r.result = {"score": s, "success_rate": 0.1, "n_test": 10, "nfe": 1,
                    "per_seed": [s + ((0.01 if j % 2 else -0.01) if "reflow" in r.slug else 0)
                                 for j in range(10)]}
        timing[r.slug] = {"p50_ms": p50.get(r.slug, 1.0), "p90_ms": 2 * p50.get(r.slug, 1.0)}
    return table, timing


def test_rows_are_every_policy_of_the_issue(budget, tmp_path):
    table, _ = made_up(budget, tmp_path)
    assert [r.slug for r in table] == ["base_rk45", "base_euler1", "base_euler2", "base_euler4",
                                       "reflow_k1", "sefa_k1", "reflow_k2", "sefa_k2", "reflow_k4",
                                       "sefa_k4", "reflowed_euler1", "reflowed_euler2",
                                       "reflowed_euler4", "ddpm100", "ddim10"]
    assert [r.slug for r in table if r.student] == ["reflow_k1", "sefa_k1", "reflow_k2", "sefa_k2",
                                                    "reflow_k4", "sefa_k4"]
    by = {r.slug: r for r in table}
    assert by["ddim10"].target.endswith("ddpm@ddim-10") and by["base_euler2"].target.endswith("base@euler-2")
    assert by["base_rk45"].solver_args == [] and by["base_rk45"].target.endswith("base@rk45")
    assert "(12.0% replaced)" in by["sefa_k2"].made_by and "--steps 2" in by["sefa_k2"].made_by


def test_each_budget_names_the_best_score_that_fits_and_differences_are_paired(budget, tmp_path):
    table, timing = made_up(budget, tmp_path)
    assert budget.best_under(table, timing, 0.5) is None
    assert budget.best_under(table, timing, 1.0).slug == "sefa_k1"  # 0.72 beats reflow-1's 0.70
    assert budget.best_under(table, timing, 3.0).slug == "sefa_k2"
    assert budget.best_under(table, timing, 10.0).slug == "sefa_k2"  # DDIM-10 fits, scores less
    report = budget.render(table, timing, {"device": "cpu", "passes": 3,
                                          "machine": {"cpu": "a CPU", "cores": 2, "python": "3.11"}}, "rows/ts1")
    lines = report.splitlines()
    assert "- **1 ms**: SeFA-1 (student, eps 0.05), 0.720 (1 ms)" in lines
    assert "- **10 ms**: SeFA-2 (student, eps 0.05), 0.790 (2 ms)" in lines
    sefa2 = next(l for l in lines if l.startswith("| SeFA-2"))
    assert "-0.010 ± 0.000" in sefa2  # 0.79 - 0.80 on every seed pair
    rows = [l for l in lines if l.startswith("| ") and not l.startswith("| policy")]
    assert len(rows) == 15 and rows[-1].startswith("| base flow, RK45")  # sorted by latency
    budget.plot(table, timing, tmp_path / "p.png")
    assert (tmp_path / "p.png").stat().st_size > 10_000
