"""benchmarks/lerobot_parity.py: the two evaluators' per-episode results, in the shapes their
files have (sefa eval's eval_log.json `per_seed`, lerobot-eval's eval_info.json `per_task`;
written here with a few episodes), to means, standard errors and the difference in them."""

from __future__ import annotations

import json
import math

import pytest

from benchmark_module import load

parity = load("lerobot_parity")


def test_means_standard_errors_and_the_difference(tmp_path):
    (tmp_path / "sefa.json").write_text(json.dumps({"per_seed": [
        {"seed": 100000, "score": 0.5, "success": False},
        {"seed": 100001, "score": 1.0, "success": True},
        {"seed": 100002, "score": 0.6, "success": False}]}))
    (tmp_path / "lerobot.json").write_text(json.dumps({"per_task": [{"task_group": "pusht", "metrics": {
        "max_rewards": [0.2, 0.4], "successes": [False, False]}}]}))
    r = parity.compare(parity.sefa_episodes(tmp_path / "sefa.json"),
                       parity.lerobot_episodes(tmp_path / "lerobot.json"))
    assert r["n"] == {"sefa": 3, "lerobot": 2}
    s = r["score"]
    assert s["sefa"] == pytest.approx(0.7) and s["lerobot"] == pytest.approx(0.3)
    assert s["sefa_se"] == pytest.approx(math.sqrt(0.07 / 3))  # sample variance 0.07
    assert s["lerobot_se"] == pytest.approx(0.1)  # std 0.1414 / sqrt(2)
    assert s["difference_se"] == pytest.approx(math.hypot(s["sefa_se"], 0.1))
    assert s["z"] == pytest.approx(-0.4 / s["difference_se"])
    assert r["success"]["sefa"] == pytest.approx(1 / 3) and r["success"]["lerobot"] == 0.0
