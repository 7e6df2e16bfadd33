"""The Push-T study's bookkeeping (benchmarks/pusht_study.py) on made-up numbers: the study
itself is not run in CI, but its rows, goal ratios, report block and plot are."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def study():
    from benchmark_module import load

    return load("pusht_study")


def made_up(study):
    table = study.rows("pipelines/pusht_lowdim.yaml", "pipelines/pusht_lowdim_train.yaml")
    scores = {"sefa_eps0.05": 0.80, "base_rk45": 0.83, "base_euler1": 0.40, "reflow1_noalign": 0.70,
              "reflow2_noalign": 0.85, "ddpm100": 0.9, "ddim10": 0.88}
    latency = {"calls": 10, "rows": []}
    for row in table:
        score = scores.get(row.slug, 0.5)
        per_seed = [score + (0.1 if i % 2 else -0.1) for i in range(50)] if row.slug.startswith("sefa") \
            else [score] * 50
        row.result = {"score": score, "success_rate": 0.1, "n_test": 50, "val_action_mse": 1000.0,
                      "nfe": 1, "per_seed": per_seed}
        p50 = {"ddpm100": 60.0, "ddim10": 6.0, "base_rk45": 170.0}.get(row.slug, 0.6)
        target = f"/w/{row.checkpoint}" + (f"@{row.setting}" if row.setting else "")
        latency["rows"].append({"target": target, "p50_ms": p50, "p90_ms": p50 * 1.1, "forward_ms": 0.55})
    return table, latency


def test_rows_cover_the_issue_and_run_in_a_cache_friendly_order(study):
    table = study.rows("P.yaml", "T.yaml")
    names = [r.name for r in table]
    assert len(names) == 10 and len(set(r.slug for r in table)) == 10
    assert {"diffusion (DDPM-100)", "diffusion (DDIM-10)", "base flow, RK45", "base flow, Euler-1",
            "reflow x1, one step, no alignment", "reflow x2, one step, no alignment"} <= set(names)
    assert [r.slug for r in table if r.slug.startswith("sefa")] == \
        ["sefa_eps0.05", "sefa_eps0.02", "sefa_eps0.1", "sefa_eps0.2"]
    # SeFA rows use reflow x1 and come before reflow x2 replaces the last reflow stage
    last_sefa = max(i for i, r in enumerate(table) if r.slug.startswith("sefa"))
    assert last_sefa < [r.slug for r in table].index("reflow2_noalign")
    assert all(["reflow", "--iters", "1"] in r.prepare for r in table[3:] if r.slug.startswith("sefa"))
    ddim = next(r for r in table if r.slug == "ddim10")
    assert ddim.solver_args() == ["--solver", "ddim", "--steps", "10"] and ddim.setting == "ddim-10"


def test_goals_are_ratios_and_paired_differences_of_the_same_run(study):
    table, latency = made_up(study)
    got = {name: cells for name, _, cells in study.goals(table, latency)}
    sefa = "SeFA one-step, eps 0.05"
    assert set(got["latency / DDPM-100 latency"]) == {f"SeFA one-step, eps {e:g}" for e in study.EPS}
    assert got["latency / DDPM-100 latency"][sefa] == (pytest.approx(0.01), None, True)
    assert got["latency / its bare forward pass"][sefa] == (pytest.approx(0.6 / 0.55), None, True)
    d, se, met = got["score - base flow RK45 score"][sefa]
    assert (d, met) == (pytest.approx(-0.03), False)  # issue 11's goal: within 0.02 of RK45
    # per-seed scores 0.8 + (-0.1, 0.1, ...) against a constant: the paired error is 0.1 / sqrt(50)
    assert se == pytest.approx(np.std([-0.1, 0.1] * 25, ddof=1) / np.sqrt(50))
    assert got["score - reflow x1 one-step (no alignment) score"][sefa][::2] == (pytest.approx(0.10), True)
    assert got["score - reflow x2 one-step (no alignment) score"][sefa][::2] == (pytest.approx(-0.05), False)


def test_sefa_beats_plain_reflow_only_by_two_paired_standard_errors(study):
    table, latency = made_up(study)
    by = {r.slug: r for r in table}
    by["sefa_eps0.05"].result = {"score": 0.71, "per_seed": [0.7, 0.72] * 25}  # +0.01 ± 0.0014
    by["reflow1_noalign"].result = {"score": 0.70, "per_seed": [0.70] * 50}
    by["reflow2_noalign"].result = {"score": 0.70, "per_seed": [0.6, 0.8] * 25}  # +0.01 ± 0.014
    got = {name: cells for name, _, cells in study.goals(table, latency)}
    assert got["score - reflow x1 one-step (no alignment) score"]["SeFA one-step, eps 0.05"][2] is True
    assert got["score - reflow x2 one-step (no alignment) score"]["SeFA one-step, eps 0.05"][2] is False


def test_paired_difference_over_the_seeds_both_ran(study):
    """500 one-step seeds against 200 RK45 seeds: the first 200 are paired, the rest unused."""
    a, b = study.Row("a", "a", [], "x"), study.Row("b", "b", [], "y")
    a.result = {"score": 0.0, "per_seed": [1.0, 0.0] * 100 + [9.0] * 300}
    b.result = {"score": 0.0, "per_seed": [0.5] * 200}
    d, se = study.paired_difference(a, b)
    assert d == pytest.approx(0.0) and se == pytest.approx(np.std([0.5, -0.5] * 100, ddof=1) / np.sqrt(200))


def test_paired_difference_without_per_seed_scores_has_no_error(study):
    a, b = study.Row("a", "a", [], "x"), study.Row("b", "b", [], "y")
    a.result, b.result = {"score": 0.5}, {"score": 0.25}
    assert study.paired_difference(a, b) == (0.25, None)


def test_per_seed_scores_are_read_from_the_workspace_relative_log_that_eval_reports(study, tmp_path, monkeypatch):
    """`sefa eval --json` gives eval_log relative to the workspace; the study runs elsewhere."""
    log = tmp_path / "ws" / "evals" / "pusht-abc" / "eval_log.json"
    log.parent.mkdir(parents=True)
    log.write_text(json.dumps({"per_seed": [{"seed": 100000, "score": 0.25}, {"seed": 100001, "score": 1.0}]}))
    monkeypatch.chdir(tmp_path)  # not the workspace
    row = study.Row("a", "a", [], "rows/a")
    row.result = {"score": 0.625, "eval_log": "evals/pusht-abc/eval_log.json"}
    study.load_per_seed(row, tmp_path / "ws")
    assert row.result["per_seed"] == [0.25, 1.0]


def test_report_replaces_only_its_own_block_and_draws_the_plot(study, tmp_path):
    table, latency = made_up(study)
    text = study.render_report("cpu", table, latency, "P.yaml", "T.yaml", "plot.png")
    assert text.count("\n| ") >= 10 + 5 and "**no**" in text and "sefa eval rows/sefa_eps0.05" in text
    # the ingest line names the store where a reader has it (pusht.zip unpacks to pusht/), not
    # the folder this study was run from
    assert "`sefa ingest pusht/pusht_cchi_v7_replay.zarr --fps 10" in text and "shared" not in text
    doc = tmp_path / "results.md"
    doc.write_text("# R\n\nprose before\n<!-- study:cpu:begin -->\nold\n<!-- study:cpu:end -->\nprose after\n"
                   "<!-- study:full:begin -->\nfull block\n<!-- study:full:end -->\n")
    study.write_between_markers(doc, "cpu", text)
    new = doc.read_text()
    assert "old" not in new and text in new
    assert new.startswith("# R\n\nprose before\n") and "prose after" in new and "full block" in new
    study.plot_scores(table, latency, tmp_path / "plot.png", "test")
    assert (tmp_path / "plot.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
