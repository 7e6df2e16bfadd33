"""benchmarks/metaworld_study.py's group table on constructed per-seed results: pooled success
rates, the student minus RK45 paired over (task, seed), the latency ratio, and a task that is
not finished left out. (The study's commands run end to end in tests/sefa_sim_tests/test_metaworld.py's
pipeline test; this checks the arithmetic of the table.)"""

from __future__ import annotations

import numpy as np
import pytest

from benchmark_module import load


@pytest.fixture(scope="module")
def study():
    return load("metaworld_study")


def entry(rows: dict[str, list[int]], latency: dict[str, float] | None = None) -> dict:
    return {"demos": 10, "rows": {slug: {"success_rate": float(np.mean(s)), "n_test": len(s),
                                         "per_seed": s} for slug, s in rows.items()},
            **({"latency": latency} if latency else {})}


def test_group_summary_pools_episodes_and_pairs_over_task_and_seed(study):
    results = {
        "reach": entry({"base_rk45": [1, 1, 0, 1], "base_euler1": [0, 0, 0, 0],
                        "sefa": [1, 0, 0, 1], "ddim10": [1, 1, 1, 1]},
                       {"base_rk45": 40.0, "base_euler1": 1.0, "sefa": 1.0, "ddim10": 10.0}),
        "push": entry({"base_rk45": [0, 1, 1, 1], "base_euler1": [1, 0, 0, 0],
                       "sefa": [0, 1, 1, 0], "ddim10": [0, 0, 1, 1]},
                      {"base_rk45": 60.0, "base_euler1": 1.0, "sefa": 2.0, "ddim10": 10.0}),
        "hammer": {"demos": 10, "rows": {}},  # not finished: left out
    }
    s = study.group_summary(results, ["reach", "push", "hammer"])
    assert s["tasks"] == ["reach", "push"]
    rk45 = [1, 1, 0, 1, 0, 1, 1, 1]
    p, se, n = s["rows"]["base_rk45"]
    assert (p, n) == (0.75, 8) and se == pytest.approx(np.std(rk45, ddof=1) / np.sqrt(8))
    diff = np.array([1, 0, 0, 1, 0, 1, 1, 0]) - np.array(rk45)
    d, dse = s["student_minus_rk45"]
    assert d == pytest.approx(diff.mean()) and dse == pytest.approx(diff.std(ddof=1) / np.sqrt(8))
    assert s["latency_ratio"] == pytest.approx(1.5 / 50.0)
    table = study.render(results)
    assert "| reach | easy | 10 | 4 |" in table and "hammer" not in table.split("Per group")[0]
    assert "| hard | 1/6 |" in table and "| easy | 1/28 |" in table and "| all | 2/50 |" in table
    assert "†" not in table  # rows without a recorded kind are taken as SeFA students


def test_a_student_whose_alignment_replaced_nothing_is_not_called_sefa(study):
    rows = {"base_rk45": [1, 0], "base_euler1": [0, 0], "sefa": [1, 1], "ddim10": [1, 0]}
    plain = entry(rows)
    plain["rows"]["sefa"]["kind"] = "reflow_one_step"
    aligned = entry(rows)
    aligned["rows"]["sefa"]["kind"] = "sefa_one_step"
    table = study.render({"push-wall": plain, "push": aligned})
    assert "| 100% ± 0% †" in table.split("| push-wall |")[1].split("\n")[0]
    assert "†" not in table.split("| push |")[1].split("\n")[0]
    assert "† push-wall: alignment replaced none of the couplings" in table
