"""`sefa choose-execution` on a tiny one-step checkpoint (trained in seconds on real Push-T
data, tests/deploy_helpers.py): it rolls out validation seeds only, never a test seed; what it
chooses is kept with the checkpoint and then run by `sefa eval`, carried by an export's
metadata.json and served by default; its bad options are one line each."""

from __future__ import annotations

import json
import shutil

import pytest

pytest.importorskip("pymunk", reason="the sim extra is not installed")


@pytest.fixture()
def ws(deploy_workspace, tmp_path):
    """A workspace of its own holding a copy of the one-step student (a choice writes into
    the checkpoint; the session's shared checkpoints stay as they are)."""
    shutil.copytree(deploy_workspace / "distill", tmp_path / "distill")
    return tmp_path


def test_the_chooser_never_rolls_out_a_test_seed(ws, monkeypatch):
    from sefa_pipelines.choose import TEST_SEEDS, ChooseRequest, choose
    from sefa_sim.pusht import PushTEnv

    seen = []
    real = PushTEnv.reset
    monkeypatch.setattr(PushTEnv, "reset", lambda self, seed: seen.append(seed) or real(self, seed))
    summary = choose(ws, ws / "distill", ChooseRequest(
        "pusht", n_val=3, max_steps=10, fps=10.0, candidates=("receding-8", "receding-1")),
        device="cpu", log=lambda s: None)
    assert sorted(seen) == sorted([200_000, 200_001, 200_002] * 2)
    assert not any(s in TEST_SEEDS for s in seen)
    assert summary["validation_seeds"] == [200_000, 200_002] and summary["episodes_run"] == 6
    assert {r["label"] for r in summary["candidates"]} == {"receding K=8", "receding K=1"}


def test_a_validation_range_reaching_the_test_seeds_is_one_line(ws):
    from cli_inprocess import run_cli

    r = run_cli("choose-execution", "distill", "--env", "pusht", "--val-start-seed", "199990",
                "--n-val", "20", "-w", ws)
    assert r.returncode == 1 and r.stderr.count("\n") == 1
    assert r.stderr.startswith("error: --val-start-seed: validation seeds 199990..200009 "
                               "overlap the test seeds (100000..199999")
    r = run_cli("choose-execution", "distill", "--env", "pusht", "--candidate", "act-1", "-w", ws)
    assert r.returncode == 1 and "--candidate: 'act-1' is not MODE[-K][xN]" in r.stderr
    r = run_cli("choose-execution", "distill", "--env", "pusht", "--min-gain-se", "-1", "-w", ws)
    assert r.returncode == 1 and r.stderr.count("\n") == 1 and "--min-gain-se" in r.stderr


def test_the_choice_is_what_eval_export_and_serve_run_by_default(ws):
    from cli_inprocess import run_cli
    from sefa_deploy.backends import load_backend
    from sefa_deploy.export import export_policy
    from sefa_deploy.server import served_execution
    from sefa_model.policy.execution import ExecutionSettings, load_choice

    r = run_cli("choose-execution", "distill", "--env", "pusht", "--n-val", "2", "--max-steps",
                "10", "--fps", "10", "--candidate", "receding-2", "--json", "-w", ws,
                "--device", "cpu")
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout)
    assert summary["chosen"] == "receding K=2" and summary["seconds"] >= 0
    chosen = ExecutionSettings("receding", 2, 1)
    assert load_choice(ws / "distill") == chosen
    r = run_cli("eval", "distill", "--env", "pusht", "--n-test", "1", "--max-steps", "10",
                "--json", "-w", ws, "--device", "cpu")
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)[0]["execution_label"] == "receding K=2"
    export_policy(ws / "distill", ws / "export", fmt="torchscript")
    meta = json.loads((ws / "export" / "metadata.json").read_text())
    assert ExecutionSettings.from_json(meta["execution"]) == chosen
    assert served_execution(load_backend(ws / "export", device="cpu").metadata, None) == chosen
    # `sefa serve CHECKPOINT` (no export) reads the record too
    assert served_execution(load_backend(ws / "distill", device="cpu").metadata, None) == chosen
    assert served_execution(meta, ExecutionSettings("ensemble")).mode == "ensemble"  # given wins


def rolled_out(scores: dict[str, list[float]], step_ms: dict[str, float] | None = None) -> list[dict]:
    """Candidates as `choose` has them after the rollouts, paired with the default's seeds."""
    from sefa_pipelines.choose import paired_with_default

    rows = [{"label": k, "scores": v, "mean_score": float(sum(v) / len(v)),
             "mean_step_ms": (step_ms or {}).get(k, 1.0)} for k, v in scores.items()]
    paired_with_default(rows, "receding K=8")
    return rows


def test_the_default_is_left_only_for_a_gain_of_min_gain_se_standard_errors():
    from sefa_pipelines.choose import pick

    default = [0.5, 0.6, 0.7, 0.8]
    noisy = [0.9, 0.4, 0.9, 0.8]  # differences 0.4, -0.2, 0.2, 0: mean 0.1, se sqrt(0.2 / 3) / 2
    rows = rolled_out({"receding K=8": default, "ensemble K=1": noisy})
    assert rows[1]["minus_default"] == pytest.approx(0.1)
    assert rows[1]["minus_default_se"] == pytest.approx((0.2 / 3) ** 0.5 / 2)
    label, why = pick(rows, "receding K=8", 2.0)
    assert label == "receding K=8"
    # the seeds at which +0.1 would reach 2 standard errors: 4 * (2 * 0.129 / 0.1) ** 2 = 26.7
    assert why == ("the default: the best on the validation seeds, ensemble K=1, is +0.100 ± "
                   "0.129 over it, less than 2 standard errors; more validation seeds would "
                   "decide it (at this gain, --n-val 27 or more)")
    assert pick(rows, "receding K=8", 0.75)[0] == "ensemble K=1"  # 0.1 >= 0.75 * 0.129
    assert pick(rows, "receding K=8", 0.0)[0] == "ensemble K=1"  # the best mean
    # every seed better by the same amount: no spread, a certain gain
    steady = rolled_out({"receding K=8": default, "receding K=4": [x + 0.05 for x in default]})
    assert pick(steady, "receding K=8", 2.0) == (
        "receding K=4", "the best on the validation seeds, +0.050 ± 0.000 over receding K=8")
    # a best level with the default (first on a cheaper step) gets no hint: no gain to resolve
    level = rolled_out({"receding K=8": default, "receding K=4": [0.6, 0.5, 0.8, 0.7]},
                       {"receding K=8": 1.0, "receding K=4": 0.5})
    assert pick(level, "receding K=8", 2.0) == ("receding K=8", (
        "the default: the best on the validation seeds, receding K=4, is +0.000 ± 0.058 over it, "
        "less than 2 standard errors"))


def test_the_chooser_picks_the_best_mean_when_it_is_the_default_or_the_default_was_not_tried():
    from sefa_pipelines.choose import pick

    rows = rolled_out({"receding K=8": [1.0, 1.0], "receding K=1": [0.0, 1.0]})
    assert pick(rows, "receding K=8", 2.0) == ("receding K=8", "the best on the validation seeds")
    # ties go to the cheaper per control step
    tie = rolled_out({"receding K=2": [1.0, 0.0], "receding K=4": [1.0, 0.0]},
                     {"receding K=2": 0.5, "receding K=4": 0.25})
    assert pick(tie, "receding K=8", 2.0) == (
        "receding K=4", "the best on the validation seeds (receding K=8 was not tried)")
