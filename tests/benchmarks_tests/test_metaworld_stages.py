"""The stage summary of benchmarks/metaworld_stages.py: every failed episode is counted in exactly
one stage, and successes in none (the rollouts themselves are `sefa eval`'s loop, tested there)."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="module")
def stages():
    from benchmark_module import load

    return load("metaworld_stages")


def row(success, near, grasped, closest):
    return {"seed": 0, "success": success, "steps": 500, "near_object": near, "grasped": grasped,
            "closest_obj_to_target": closest}


def test_each_failed_episode_falls_in_one_stage(stages):
    rows = [row(True, True, True, 0.01), row(False, False, False, 0.5), row(False, True, False, 0.4),
            row(False, True, True, 0.1), row(False, False, True, 0.2)]
    s = stages.summary(rows)
    assert s["success_rate"] == pytest.approx(0.2)
    assert (s["failed"], s["failed_never_near"], s["failed_near_never_grasped"], s["failed_grasped"]) == (4, 1, 1, 2)
    assert s["failed_never_near"] + s["failed_near_never_grasped"] + s["failed_grasped"] == s["failed"]
    assert s["failed_median_closest"] == pytest.approx(0.3)


def test_no_failures_has_no_median(stages):
    assert stages.summary([row(True, True, True, 0.0)])["failed_median_closest"] is None
