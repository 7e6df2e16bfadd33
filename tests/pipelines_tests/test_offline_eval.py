"""Offline evaluation's numbers add up (issue 25, trap 7), through the real `sefa` command on
the KUKA LWR MCAP recording (../shared/data): one episode whose arm holds still for a while, so
the nearest training windows' chunks are identical and the expert spread is about zero.

- the mean-action baseline stands beside the policy (there it beats a tiny policy);
- a spread ratio over an expert spread of about zero is not printed as a huge number;
- `sefa eval --offline` reports the same action MSE (and mean-action MSE) as training's
  validation of the same checkpoint: one definition, the same windows, noise and seed.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from sefa_inprocess import kuka_workspace, sefa

@pytest.fixture(scope="module")
def kuka_ws(shared_data, tmp_path_factory) -> Path:
    return kuka_workspace(shared_data, tmp_path_factory.mktemp("kuka"))


def test_offline_eval_is_trainings_validation_with_the_mean_action_beside_it(kuka_ws):
    val = json.loads((kuka_ws / "train/manifest.json").read_text())["summary"]["val"]
    (row,) = json.loads(sefa("eval", "--offline", "--json", "-w", kuka_ws).stdout)
    # the same windows, noise and seed as training's validation: the same numbers
    assert row["windows"] == 12 and row["split"] == "valid (window-level)"
    assert row["action_mse"] == pytest.approx(val["val_action_mse"], rel=1e-5)
    assert row["mean_action_mse"] == pytest.approx(val["val_mean_action_mse"], rel=1e-9)
    # the arm holds still: the expert spread is about zero and no ratio is made of it
    assert row["expert_spread"] < 1e-3 and row["spread"] > 1e-2
    assert row["spread_ratio"] is None and "ratio is meaningless" in row["spread_note"]

    table = sefa("eval", "--offline", "-w", kuka_ws).stdout  # read back from the cache
    assert "mean-action MSE" in table and f"{row['mean_action_mse']:.4g}" in table
    assert "(no ratio)" in table and "ratio is meaningless" in table
    if row["mean_action_mse"] <= row["action_mse"]:
        assert "mean action beats train/checkpoints/latest" in table
    status = sefa("status", "-w", kuka_ws).stdout
    assert "(no ratio)" in status and "mean action" in status


def test_more_windows_or_samples_are_said_and_keep_sample_zero(kuka_ws):
    """More samples per window change the spread, not sample 0 (the action MSE)."""
    (k8,) = json.loads(sefa("eval", "--offline", "--json", "-w", kuka_ws).stdout)
    (k2,) = json.loads(sefa("eval", "--offline", "--samples", "2", "--json", "-w", kuka_ws).stdout)
    assert k2["samples"] == 2 and k8["samples"] == 8
    assert k2["action_mse"] == pytest.approx(k8["action_mse"], rel=1e-5)
    (w30,) = json.loads(sefa("eval", "--offline", "--windows", "30", "--json", "-w", kuka_ws).stdout)
    assert w30["windows"] == 30
