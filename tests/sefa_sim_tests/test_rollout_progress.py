"""Rollouts report their start (0 episodes done) before the first episode: the progress
display's rate then counts the first episode's time. Reported first after episode 1, that
episode counted as taking no time, and the ETA came out too short (2:48 for a run of 4:25).
Push-T rollouts of the deployment tests' tiny one-step student."""

from __future__ import annotations

import pytest

from sefa_model.progress import listening


def test_rollouts_report_their_start_and_the_eta_counts_the_first_episode(deploy_workspace,
                                                                          capsys):
    pytest.importorskip("pymunk", reason="the sim extra is not installed")
    from sefa_cli.console import TrainProgress
    from sefa_sim.rollouts import evaluate_pusht

    seen = []
    with listening(lambda task, done, total, fields: seen.append((task, done, total))):
        evaluate_pusht(deploy_workspace / "distill", n_test=3, max_steps=5, device="cpu")
    assert [(d, n) for task, d, n in seen if task == "rollouts"] == [(0, 3), (1, 3), (2, 3), (3, 3)]

    # the display's ETA after 2 of 4 episodes of 10 s each, reported as rollouts report: 20 s
    clock = iter([0.0, 10.0, 20.0])
    progress = TrainProgress(enabled=True)
    progress.tty, progress._now = False, lambda: next(clock)
    capsys.readouterr()
    for done in (0, 1, 2):
        progress.update("rollouts", done, 4, {})
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert last.startswith("rollouts 2/4 (50%)") and last.endswith("ETA 0:20"), last
