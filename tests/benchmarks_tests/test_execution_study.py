"""benchmarks/execution_study.py's Meta-World bookkeeping on a constructed study.json: the
chosen execution read back as a spec and evaluated on the test seeds, the headline blocks of a
task before the rest, and the per-group comparison (the student under its chosen execution
minus RK45 under its best, paired over (task, seed)) with an unfinished task left out. (The
study's commands are `sefa` commands the CLI tests cover; this checks its plan and arithmetic.)"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from benchmark_module import load


@pytest.fixture(scope="module")
def es():
    return load("execution_study")


def choice(label: str, settings: dict) -> dict:
    """What `sefa choose-execution --json` prints, reduced to what the study reads."""
    return {"chosen": label, "candidates": [
        {"label": "receding K=8", "settings": {"mode": "receding", "replan_every": 8, "samples": 1}},
        {"label": label, "settings": settings}]}


def block(task: str, scores: list[float], first: int = 100_000) -> dict:
    return {"per_seed": [{"task": task, "seed": first + i, "score": s, "success": s == 1.0}
                         for i, s in enumerate(scores)]}


def test_the_chosen_execution_is_read_back_as_a_spec(es):
    entry = {"choices": {"sefa": choice("bid K=2 N=16", {"mode": "bid", "replan_every": 2,
                                                         "samples": 16})}}
    assert es.chosen_spec(entry, "sefa") == "bid-2x16"
    entry = {"choices": {"sefa": choice("receding K=4", {"mode": "receding", "replan_every": 4,
                                                         "samples": 1})}}
    assert es.chosen_spec(entry, "sefa") == "receding-4"
    assert es.chosen_spec({"choices": {"sefa": {"chosen": None, "error": "x"}}}, "sefa") is None
    assert es.chosen_spec({}, "sefa") is None


def test_a_choice_recorded_before_the_two_standard_error_rule_is_made_again_by_it(es):
    """Push-T's record: the best mean on validation, ACT's ensembling, +0.014 ± 0.040 over 8
    per prediction, is not 2 standard errors above it, so the default stands; reach's receding
    every 4 steps, +0.10 ± 0.043, is."""
    def record(gain, se, why=None):
        rows = [{"label": "receding K=8", "mean_score": 0.736, "mean_step_ms": 0.1,
                 "settings": {"mode": "receding", "replan_every": 8, "samples": 1}},
                {"label": "ensemble K=1", "mean_score": 0.736 + gain, "mean_step_ms": 1.0,
                 "minus_default": gain, "minus_default_se": se,
                 "settings": {"mode": "ensemble", "replan_every": 1, "samples": 1}},
                {"label": "coherent K=1 N=16", "settings": {"mode": "coherent",
                                                            "replan_every": 1, "samples": 16}}]
        return {"choices": {"sefa": {"chosen": "ensemble K=1", "candidates": rows,
                                     **({"why": why} if why else {})}}}

    assert es.chosen_spec(record(0.014, 0.040), "sefa") == "receding-8"
    assert es.chosen_spec(record(0.10, 0.043), "sefa") == "ensemble-1"
    # a record made under the rule is taken as it is
    assert es.chosen_spec(record(0.014, 0.040, why="given"), "sefa") == "ensemble-1"


def test_a_task_gets_its_headline_blocks_first_and_a_chosen_execution_outside_the_grid(es):
    study = es.Study(Path("/nonexistent"))
    key = "metaworld:reach"
    study.state[key] = {"choices": {"sefa": choice("bid K=2 N=16", {
        "mode": "bid", "replan_every": 2, "samples": 16})}, "blocks": {}}
    latency = {"decisions": [{"target": "distill", "samples": 1, "p50_ms": 1.0},
                             {"target": "distill", "samples": 16, "p50_ms": 2.0},
                             {"target": "train@rk45", "samples": 1, "p50_ms": 200.0}]}
    seeds = {False: 50, True: 50}
    todo = study.blocks(key, Path("ws"), key, es.ROWS, seeds, 50, set(), latency, 500,
                        es.META_GRID, es.HEADLINE)
    assert {(b[1].slug, b[2]) for b in todo} == {("sefa", "bid-2x16"), ("sefa", "receding-8"),
                                                ("base_rk45", "receding-8")}
    everything = study.blocks(key, Path("ws"), key, es.ROWS, seeds, 50, set(), latency, 500,
                              es.META_GRID, None)
    pairs = {(b[1].slug, b[2]) for b in everything}
    assert pairs == {("sefa", s) for s in (*es.EXECUTIONS, "bid-2x16")} | {
        ("base_rk45", s) for s in ("receding-8", "receding-4", "receding-2")} | {
        ("base_euler10", "receding-8"), ("base_euler10", "receding-1"), ("ddim10", "receding-8")}
    costs = [b[0] for b in everything]
    assert costs == sorted(costs)  # cheapest first
    study.state[key]["blocks"]["sefa|receding-8|100000"] = block("reach", [1.0] * 50)
    again = study.blocks(key, Path("ws"), key, es.ROWS, seeds, 50, set(), latency, 500,
                         es.META_GRID, es.HEADLINE)
    assert {(b[1].slug, b[2]) for b in again} == {("sefa", "bid-2x16"), ("base_rk45", "receding-8")}


def test_each_group_pairs_the_chosen_student_with_rk45s_best_over_task_and_seed(es):
    def task(chosen, s8, rk8, rk4, spec="receding-4"):
        mode, k = spec.split("-")
        return {"choices": {"sefa": choice(f"{mode} K={k}", {"mode": mode, "replan_every": int(k),
                                                             "samples": 1})},
                "blocks": {f"sefa|{spec}|100000": block(t, chosen),
                           "sefa|receding-8|100000": block(t, s8),
                           "base_rk45|receding-8|100000": block(t, rk8),
                           "base_rk45|receding-4|100000": block(t, rk4)}}

    t = "reach"
    state = {"metaworld:reach": task([1, 1, 1, 0], [1, 0, 1, 0], [1, 1, 0, 0], [1, 1, 1, 0])}
    t = "door-open"  # RK45's best here is 8 per prediction
    state["metaworld:door-open"] = task([0, 1, 1, 1], [0, 1, 0, 1], [1, 1, 1, 1], [1, 0, 1, 1],
                                        spec="receding-2")
    t = "button-press"  # RK45 not done: left out
    state["metaworld:button-press"] = {"blocks": {"sefa|receding-8|100000": block(t, [1, 1, 1, 1])}}
    lines = {g["group"]: g for g in es.group_summary(state, n=4)}
    easy = lines["easy"]
    assert (easy["tasks"], easy["of"]) == (2, 28)
    # (task, seed) pairs in the order the tasks come in the group: button-press, door-open, reach
    student = np.array([0, 1, 1, 1] + [1, 1, 1, 0])
    teacher = np.array([1, 1, 1, 1] + [1, 1, 1, 0])
    diff = student - teacher
    assert easy["student_chosen"] == pytest.approx(student.mean())
    assert easy["rk45_best"] == pytest.approx(teacher.mean())
    assert easy["minus"][0] == pytest.approx(diff.mean())
    assert easy["minus"][1] == pytest.approx(diff.std(ddof=1) / np.sqrt(8))
    d8 = np.array([0, 1, 0, 1] + [1, 0, 1, 0]) - np.array([1, 1, 1, 1] + [1, 1, 0, 0])
    assert easy["minus_receding8"][0] == pytest.approx(d8.mean())
    assert lines["medium"]["tasks"] == 0 and "minus" not in lines["medium"]
    assert lines["all"]["tasks"] == 2 and lines["all"]["of"] == 50
    # RK45 picked on the other half of the seeds: door-open's 8 per prediction both ways;
    # reach's first half under every 4 steps (better on seeds 2, 3), its second half under 8
    # per prediction (a tie on seeds 0, 1 goes to the execution listed first)
    cross = np.array([1, 1, 1, 1] + [1, 1, 0, 0])
    assert easy["rk45_cross"] == pytest.approx(cross.mean())
    assert easy["minus_cross"][0] == pytest.approx((student - cross).mean())
    assert easy["minus_cross"][1] == pytest.approx((student - cross).std(ddof=1) / np.sqrt(8))


def test_the_policy_is_told_from_the_choice_of_its_execution(es):
    """choice_table: the student chosen on validation seeds, its grid's best picked on the other
    half of the test seeds and in hindsight, against RK45 picked the same two ways, on the tasks
    whose grids are whole."""
    zeros = [0, 0, 0, 0]
    student = {spec: zeros for spec in es.META_GRID["sefa"]}
    student |= {"receding-4": [1, 0, 0, 0], "receding-1": [0, 0, 1, 1]}
    rk45 = {"receding-8": [1, 1, 0, 0], "receding-4": [1, 1, 1, 0], "receding-2": zeros}
    blocks = {f"sefa|{sp}|100000": block("reach", s) for sp, s in student.items()}
    blocks |= {f"base_rk45|{sp}|100000": block("reach", s) for sp, s in rk45.items()}
    state = {"metaworld:reach": {"choices": {"sefa": choice("receding K=4", {
                 "mode": "receding", "replan_every": 4, "samples": 1})}, "blocks": blocks},
             "metaworld:door-open": {"choices": {}, "blocks": {  # its grid not whole: left out
                 "sefa|receding-8|100000": block("door-open", zeros),
                 "base_rk45|receding-8|100000": block("door-open", zeros)}}}
    easy = {g["group"]: g for g in es.choice_table(state, n=4)}["easy"]
    assert (easy["tasks"], easy["of"]) == (1, 28)
    # the student: seeds 0-1 picked on seeds 2-3 (every step, 2 of 2) score 0, 0; seeds 2-3
    # picked on seeds 0-1 (every 4 steps, 1 of 2) score 0, 0; in hindsight every step, 0, 0, 1, 1
    # RK45: seeds 0-1 under every 4 steps (1 of 2 on seeds 2-3), seeds 2-3 under 8 per
    # prediction (a tie with every 4 steps on seeds 0-1): 1, 1, 0, 0; in hindsight every 4 steps
    assert [easy[k] for k in ("student_chosen", "student_cross", "student_hindsight",
                              "rk45_cross", "rk45_hindsight")] == [0.25, 0.0, 0.5, 0.5, 0.75]
    assert easy["chosen_minus_rk45_cross"][0] == pytest.approx(-0.25)
    assert easy["cross_minus_rk45_cross"][0] == pytest.approx(-0.5)
    d = np.array([0, 0, 1, 1]) - np.array([1, 1, 1, 0])
    assert easy["hindsight_minus_rk45_hindsight"][0] == pytest.approx(d.mean())
    assert easy["hindsight_minus_rk45_hindsight"][1] == pytest.approx(d.std(ddof=1) / 2)
    assert {g["group"]: g for g in es.choice_table(state, n=4)}["medium"]["tasks"] == 0
    text = es.markdown(state, n=4)
    assert ("| easy | 1 of 28 | 25.0 % | 0.0 % | 50.0 % | 50.0 % | 75.0 % | -25.0 ± 25.0 | "
            "-50.0 ± 28.9 | -25.0 ± 47.9 |") in text
    del state["metaworld:reach"]["blocks"]["sefa|bid-1x16|100000"]
    assert "picked on the other half | in hindsight" not in es.markdown(state, n=4)


def test_rk45_picked_on_the_other_half_has_no_hindsight_bonus(es):
    """Each half of the seeds is scored under the execution best on the other half: a lucky
    execution that wins only on the seeds it is scored on is not picked for them."""
    s = lambda xs: {("t", 100_000 + i): float(x) for i, x in enumerate(xs)}
    per_spec = {"receding-8": s([1, 0, 1, 0, 1, 1]), "receding-4": s([0, 1, 0, 1, 1, 0])}
    # seeds 0-2 picked on seeds 3-5: a tie (2 of 3 each), to 8 per prediction, listed first;
    # seeds 3-5 picked on seeds 0-2: 8 per prediction (2 of 3 against 1 of 3)
    assert es.cross_picked(per_spec) == per_spec["receding-8"]
    # every 4 steps wins on seeds 0-2 only: picked in hindsight it would score them (3 of 3);
    # here it runs seeds 3-5, where it lost, and seeds 0-2 run 8 per prediction
    per_spec["receding-4"] = s([1, 1, 1, 0, 0, 0])
    got = es.cross_picked(per_spec)
    assert [got[("t", 100_000 + i)] for i in range(6)] == [1, 0, 1, 0, 0, 0]
    per_spec["receding-4"] = s([1, 1, 1, 1, 1, 1])  # best on both halves: picked for both
    got = es.cross_picked(per_spec)
    assert [got[("t", 100_000 + i)] for i in range(6)] == [1, 1, 1, 1, 1, 1]


def test_the_full_table_per_group_pairs_each_execution_with_the_same_row_at_8(es):
    """Each row and execution over the group's tasks where it is done; the student's chosen
    execution is each task's own; the difference from 8 per prediction pairs (task, seed) on the
    tasks where both are done."""
    def entry(task, chosen_k, blocks):
        return {"choices": {"sefa": choice(f"receding K={chosen_k}", {
                    "mode": "receding", "replan_every": chosen_k, "samples": 1})},
                "blocks": {name: block(task, s) for name, s in blocks.items()}}

    state = {"metaworld:reach": entry("reach", 4, {
                 "sefa|receding-8|100000": [1, 0, 1, 0], "sefa|receding-4|100000": [1, 1, 1, 0],
                 "sefa|receding-1|100000": [0, 0, 1, 0]}),
             "metaworld:door-open": entry("door-open", 2, {
                 "sefa|receding-8|100000": [1, 1, 0, 0], "sefa|receding-2|100000": [1, 1, 1, 1],
                 "sefa|receding-1|100000": [1, 1]}),  # half done: left out
             "metaworld:button-press": entry("button-press", 8, {
                 "sefa|receding-4|100000": [1, 1, 1, 1]})}  # no receding-8: unpaired
    lines = {(g["group"], g["row"], g["execution"]): g for g in es.group_table(state, n=4)}
    chosen = lines[("easy", "sefa", "chosen")]
    assert (chosen["tasks"], chosen["of"]) == (2, 28)  # button-press's choice has no block
    assert chosen["score"] == pytest.approx(np.mean([1, 1, 1, 0, 1, 1, 1, 1]))
    d = np.array([1, 1, 1, 1, 1, 1, 1, 0]) - np.array([1, 1, 0, 0, 1, 0, 1, 0])  # door, reach
    assert chosen["minus_receding8"][0] == pytest.approx(d.mean())
    assert chosen["minus_receding8"][1] == pytest.approx(d.std(ddof=1) / np.sqrt(8))
    r4 = lines[("easy", "sefa", "receding-4")]
    assert r4["tasks"] == 2 and r4["paired_tasks"] == 1
    assert r4["score"] == pytest.approx(np.mean([1, 1, 1, 0, 1, 1, 1, 1]))
    assert r4["minus_receding8"][0] == pytest.approx(np.mean([0, 1, 0, 0]))
    r1 = lines[("easy", "sefa", "receding-1")]
    assert r1["tasks"] == 1 and r1["score"] == pytest.approx(0.25)
    assert "minus_receding8" not in lines[("easy", "sefa", "receding-8")]
    assert lines[("all", "sefa", "chosen")]["of"] == 50
    assert not any(g == "medium" for g, _, _ in lines)


def test_the_docs_tables_hold_the_groups_every_execution_and_the_choices(es):
    """report --markdown: the headline per group in points, each row and execution per group
    (paired against 8 per prediction, [k of m] while tasks are missing), the choices counted."""
    def entry(task, spec, blocks):
        mode, k = spec.split("-")
        return {"choices": {"sefa": choice(f"{mode} K={k}", {"mode": mode, "replan_every": int(k),
                                                             "samples": 1})},
                "blocks": {name: block(task, s) for name, s in blocks.items()}}

    state = {"metaworld:reach": entry("reach", "receding-4", {
                 "sefa|receding-8|100000": [1, 0, 1, 0], "sefa|receding-4|100000": [1, 1, 1, 0],
                 "base_rk45|receding-8|100000": [1, 1, 0, 0]}),
             "metaworld:hammer": entry("hammer", "receding-8", {  # medium
                 "sefa|receding-8|100000": [0, 0, 1, 0],
                 "base_rk45|receding-8|100000": [0, 1, 1, 0]})}
    text = es.markdown(state, n=4).splitlines()
    assert text[2] == ("| easy | 1 of 28 | 75.0 % | 50.0 % | +25.0 ± 25.0 | +0.0 ± 40.8 | "
                       "50.0 % | +25.0 ± 25.0 |")
    assert text[3] == ("| medium | 1 of 11 | 25.0 % | 50.0 % | -25.0 ± 25.0 | -25.0 ± 25.0 | "
                       "50.0 % | -25.0 ± 25.0 |")
    assert text[4] == "| hard | 0 of 6 | | | | | | |"
    assert text[5] == "| very hard | 0 of 5 | | | | | | |"
    rows = {line.split(" | ")[1]: line for line in text if line.startswith("| SeFA one-step")}
    assert rows["receding, every 4 steps"] == (
        "| SeFA one-step | receding, every 4 steps | 75.0 % (+25.0 ± 25.0) [1 of 28] |  |  |  | "
        "75.0 % (+25.0 ± 25.0) [1 of 50] |")
    assert rows["chosen per task"].endswith("| 50.0 % (+12.5 ± 12.5) [2 of 50] |")
    assert "| receding, every 4 steps | 1 | 0 | 0 | 0 | 1 |" in text
    assert "| 8 per prediction | 0 | 1 | 0 | 0 | 1 |" in text
    assert es.spec_words("bid-1x16") == "BID of 16, every step"


def test_the_docs_task_table_pairs_each_tasks_chosen_student_with_rk45s_best(es):
    """Task by task, in group order: the student's chosen execution and score, its score at 8
    per prediction, RK45's best execution (in hindsight over those done) and the paired
    difference over the task's seeds; a task without its headline is left out."""
    state = {"metaworld:reach": {
                 "choices": {"sefa": choice("receding K=4", {"mode": "receding",
                                                             "replan_every": 4, "samples": 1})},
                 "blocks": {name: block("reach", s) for name, s in {
                     "sefa|receding-8|100000": [1, 0, 1, 0],
                     "sefa|receding-4|100000": [1, 1, 1, 0],
                     "base_rk45|receding-8|100000": [1, 1, 0, 0],
                     "base_rk45|receding-4|100000": [1, 1, 1, 1]}.items()}},
             "metaworld:hammer": {"blocks": {  # no RK45 yet: left out
                 "sefa|receding-8|100000": block("hammer", [0, 0, 1, 0])}}}
    lines = es.task_table(state, n=4)
    assert [t["task"] for t in lines] == ["reach"]
    reach = lines[0]
    assert (reach["chosen"], reach["rk45_spec"]) == ("receding-4", "receding-4")
    assert (reach["student_chosen"], reach["student_receding8"], reach["rk45_best"]) == (
        0.75, 0.5, 1.0)
    d = np.array([1, 1, 1, 0]) - np.array([1, 1, 1, 1])
    assert reach["minus"][0] == pytest.approx(d.mean())
    assert reach["minus"][1] == pytest.approx(d.std(ddof=1) / 2)
    text = es.markdown(state, n=4).splitlines()
    assert text[-1] == ("| reach | easy | receding, every 4 steps | 75 % | 50 % | "
                        "100 % (receding, every 4 steps) | -25 ± 25 |")


def test_image_push_t_is_built_from_its_camera_and_studied_as_push_t(es, tmp_path, monkeypatch):
    """The image variant ingests the camera with the state and action, runs its own pipeline and
    a diffusion baseline with its base flow's settings, then the grid on Push-T (its period)."""
    study = es.Study(tmp_path)
    commands = []
    monkeypatch.setattr(study, "sefa", lambda args, ws=None, **kw: commands.append(
        ([str(a) for a in args], ws)))
    grids = []
    monkeypatch.setattr(es, "grid", lambda *a, **kw: grids.append((a[1], a[2], a[3], kw)))
    es.pusht(study, type("Args", (), {"part": "pusht_image"})())
    ws = tmp_path / "pusht_image"
    assert commands == [
        (["ingest", str(es.PUSHT_STORE), "--fps", "10", "--key", "img", "--key", "state",
          "--key", "action"], ws),
        (["run", "pipelines/pusht_image.yaml", "--threads", "1"], ws),
        (["train", "pipelines/pusht_image_train.yaml", "--objective", "ddpm", "--out",
          str(ws / "ddpm"), "--threads", "1"], ws)]
    assert grids == [("pusht_image", ws, "pusht", {"steps": 300, "table": es.IMAGE_GRID})]
    for part in es.PUSHT.values():  # every variant's files exist
        assert all((es.REPO / f).is_file() for f in (part.pipeline, part.train_config))


def faked_grid(study, monkeypatch, choices: dict) -> tuple[list, object]:
    """The study's choosers and blocks faked: a chooser records choices[row] for each row it
    runs for, a block scores 1.0 on every seed. -> (the calls in order, the grid's args: 2 seeds
    of each kind in blocks of 2)."""
    calls = []

    def choose(key, ws, env, rows, n_val):
        for row in rows:
            study.state[key].setdefault("choices", {}).setdefault(row.slug, choices[row.slug])
        calls.append(("choose", tuple(r.slug for r in rows)))

    def run_block(key, ws, env, row, spec, first, n):
        calls.append((row.slug, spec))
        study.state[key]["blocks"][f"{row.slug}|{spec}|{first}"] = block("", [1.0] * n, first)

    monkeypatch.setattr(study, "choose", choose)
    monkeypatch.setattr(study, "run_block", run_block)
    args = type("Args", (), {"n_one_step": 2, "n_multi_step": 2, "block": 2, "skip": None,
                             "n_val": 2})()
    return calls, args


def test_push_t_runs_its_headline_before_the_other_rows(es, tmp_path, monkeypatch):
    """The student and RK45 are chosen for first; then the student's chosen execution and 8
    per prediction, and RK45 under each execution whose decision fits the 100 ms period (p99 at
    its N; 16 samples at 180 ms do not); only then the other rows' choosers and the rest."""
    study = es.Study(tmp_path)
    study.state["pusht"] = {"latency": {"decisions": [
        {"target": t, "samples": n, "p50_ms": ms, "p99_ms": ms}
        for t, n, ms in (("distill", 1, 1.0), ("distill", 16, 2.0), ("train@rk45", 1, 70.0),
                         ("train@rk45", 16, 180.0), ("train@euler-10", 1, 5.0),
                         ("train@euler-10", 16, 15.0), ("ddpm@ddim-10", 1, 8.0),
                         ("ddpm@ddim-10", 16, 20.0), (es.WEAK, 16, 1.0))]}}
    ensemble = choice("ensemble K=1", {"mode": "ensemble", "replan_every": 1, "samples": 1})
    calls, args = faked_grid(study, monkeypatch, {r.slug: ensemble for r in es.ROWS})
    es.grid(study, "pusht", tmp_path, "pusht", args, steps=300)
    second = calls.index(("choose", tuple(r.slug for r in es.ROWS)))
    assert calls[0] == ("choose", ("sefa", "base_rk45"))
    assert set(calls[1:second]) == {("sefa", "ensemble-1"), ("sefa", "receding-8")} | {
        ("base_rk45", s) for s in ("receding-8", "receding-4", "receding-2", "receding-1",
                                   "ensemble-1")}
    assert len(calls[1:second]) == 7  # one block each
    rest = set(calls[second + 1:])
    assert ("base_rk45", "coherent-1x16") in rest and ("ddim10", "receding-8") in rest
    assert not rest & set(calls[1:second])
    assert len(calls) == 1 + 7 + 1 + (4 * len(es.EXECUTIONS) - 7)


def test_push_t_pairs_the_chosen_student_with_rk45s_best_real_time_execution(es):
    """RK45 every 2 steps is its best real-time score; every step with 16 samples scores higher
    but does not fit the 100 ms period, and every 4 steps is not done on the seeds yet."""
    latency = {"decisions": [{"target": "train@rk45", "samples": 1, "p99_ms": 70.0},
                             {"target": "train@rk45", "samples": 16, "p99_ms": 180.0}]}
    entry = {"latency": latency,
             "choices": {"sefa": choice("receding K=8", {"mode": "receding", "replan_every": 8,
                                                         "samples": 1}),
                         "base_rk45": choice("receding K=8", {"mode": "receding",
                                                              "replan_every": 8, "samples": 1})},
             "blocks": {"sefa|receding-8|100000": block("", [0.5, 0.7, 0.9, 0.1, 0.3]),
                        "base_rk45|receding-8|100000": block("", [0.6, 0.6, 0.6, 0.6]),
                        "base_rk45|receding-2|100000": block("", [0.9, 0.8, 0.7, 0.6]),
                        "base_rk45|receding-4|100000": block("", [1.0, 1.0]),
                        "base_rk45|coherent-1x16|100000": block("", [1.0, 1.0, 1.0, 1.0])}}
    line = es.pusht_summary(entry, 4)
    student = np.array([0.5, 0.7, 0.9, 0.1])
    d = student - np.array([0.9, 0.8, 0.7, 0.6])
    assert (line["student"], line["spec_best"], line["spec_rk45_chosen"]) == (
        "receding-8", "receding-2", "receding-8")
    assert line["minus_best"][0] == pytest.approx(d.mean())
    assert line["minus_best"][1] == pytest.approx(d.std(ddof=1) / 2)
    assert line["minus_rk45_chosen"][0] == pytest.approx((student - 0.6).mean())
    assert "minus_best" not in es.pusht_summary(entry, 5)  # no RK45 row on 5 seeds


def test_image_push_t_runs_its_smaller_grid_with_rk45_in_simulation_as_the_bar(
        es, tmp_path, monkeypatch):
    """From the camera no RK45 decision fits the 100 ms period: the headline takes RK45 at 8
    per prediction, only the student and RK45 are chosen for, and the rest is IMAGE_GRID's
    blocks, no execution outside it."""
    study = es.Study(tmp_path)
    study.state["pusht_image"] = {"latency": {"decisions": [
        {"target": t, "samples": n, "p50_ms": ms, "p99_ms": ms}
        for t, n, ms in (("distill", 1, 6.0), ("distill", 16, 9.0), ("train@rk45", 1, 380.0),
                         ("train@rk45", 16, 900.0), ("train@euler-10", 1, 21.0),
                         ("ddpm@ddim-10", 1, 25.0), (es.WEAK, 16, 6.0))]}}
    calls, args = faked_grid(study, monkeypatch, {
        "sefa": choice("receding K=2", {"mode": "receding", "replan_every": 2, "samples": 1}),
        "base_rk45": {"chosen": None, "error": "no execution fits the budget"}})
    es.grid(study, "pusht_image", tmp_path, "pusht", args, steps=300, table=es.IMAGE_GRID)
    assert calls[0] == ("choose", ("sefa", "base_rk45"))
    assert set(calls[1:4]) == {("sefa", "receding-2"), ("sefa", "receding-8"),
                               ("base_rk45", "receding-8")}
    assert [c for c in calls if c[0] == "choose"] == [calls[0]]  # no other row chosen for
    assert sorted(calls[1:]) == sorted((slug, spec) for slug, specs in es.IMAGE_GRID.items()
                                       for spec in specs)


def test_push_t_without_a_real_time_rk45_pairs_the_student_with_its_best_in_simulation(es):
    """No RK45 decision fits the period (380 ms at N = 1): the bar is its best execution done on
    the seeds, and the report says it is not real time; with one that fits, it is that one's."""
    entry = {"latency": {"decisions": [{"target": "train@rk45", "samples": 1, "p99_ms": 380.0}]},
             "choices": {"sefa": choice("receding K=8", {"mode": "receding", "replan_every": 8,
                                                         "samples": 1})},
             "blocks": {"sefa|receding-8|100000": block("", [0.5, 0.7, 0.9]),
                        "base_rk45|receding-8|100000": block("", [0.6, 0.6, 0.6]),
                        "base_rk45|receding-4|100000": block("", [0.9, 0.8, 0.4])}}
    line = es.pusht_summary(entry, 3)
    assert (line["rk45_real_time"], line["spec_best"]) == (False, "receding-4")
    assert line["minus_best"][0] == pytest.approx(np.mean([0.5 - 0.9, 0.7 - 0.8, 0.9 - 0.4]))
    assert "minus_rk45_chosen" not in line
    entry["latency"]["decisions"][0]["p99_ms"] = 70.0
    line = es.pusht_summary(entry, 3)
    assert (line["rk45_real_time"], line["spec_best"]) == (True, "receding-4")
    del entry["latency"]
    line = es.pusht_summary(entry, 3)  # not known: the best in simulation, said so
    assert (line["rk45_real_time"], line["spec_best"]) == (None, "receding-4")


def test_seed_blocks_cover_the_seeds_not_yet_recorded(es):
    first = es.FIRST_TEST_SEED
    assert es.seed_blocks(set(), 50, 50) == [(first, 50)]
    assert es.seed_blocks(set(), 25, 10) == [(first, 10), (first + 10, 10), (first + 20, 5)]
    done = {first + i for i in (*range(0, 10), 12, 13)}
    assert es.seed_blocks(done, 20, 50) == [(first + 10, 2), (first + 14, 6)]
    assert es.seed_blocks({first + i for i in range(50)}, 50, 10) == []


def test_a_study_resumed_with_another_block_size_repeats_no_seed(es):
    """Seeds 100000..100009 ran as a block of 10; resumed with --block 50, the rest is one block
    of 40 (planned from the block names, seeds 100010.. would have been thought undone, and
    seeds 100000.. would have run again as a block of 50 named like the first)."""
    study = es.Study(Path("/nonexistent"))
    key = "metaworld:reach"
    study.state[key] = {"blocks": {"base_rk45|receding-2|100000": block("reach", [1.0] * 10)}}
    latency = {"decisions": []}
    only = (("base_rk45", "receding-2"),)
    todo = study.blocks(key, Path("ws"), key, es.ROWS, {False: 50, True: 50}, 50, set(), latency,
                        500, es.META_GRID, only)
    assert [(b[3], b[4]) for b in todo] == [(100_010, 40)]


def test_a_seed_recorded_twice_stops_the_report_with_one_line(es):
    entry = {"blocks": {"sefa|receding-8|100000": block("reach", [1.0] * 20),
                        "sefa|receding-8|100010": block("reach", [0.0] * 10, 100_010)}}
    with pytest.raises(SystemExit, match="sefa receding-8: seed 100010 is recorded in more than one"):
        es.collected(entry)


def test_jobs_run_blocks_at_once_and_each_block_once(es, tmp_path, monkeypatch):
    """--jobs 2: two blocks in flight together (a barrier both must reach), every block of the
    grid recorded exactly once, none started twice."""
    import threading

    study = es.Study(tmp_path, jobs=2)
    study.state["pusht"] = {"latency": {"decisions": []}, "blocks": {}}
    together = threading.Barrier(2, timeout=10)
    started = []

    def run_block(key, ws, env, row, spec, first, n):
        name = f"{row.slug}|{spec}|{first}"
        started.append(name)
        if len(started) <= 2:
            together.wait()  # raises BrokenBarrierError if the blocks ran one at a time
        with study.lock:
            study.record(key, name, block("", [1.0] * n, first))

    monkeypatch.setattr(study, "run_block", run_block)
    only = (("sefa", "receding-8"), ("sefa", "receding-4"))
    es.run_blocks(study, {"pusht": (tmp_path, "pusht")}, {False: 6, True: 2}, 2, set(), only, 300)
    expected = {f"sefa|{s}|{100_000 + i}" for s in ("receding-8", "receding-4") for i in (0, 2, 4)}
    assert sorted(started) == sorted(expected)
    assert set(study.state["pusht"]["blocks"]) == expected
    assert set(es.json.loads((tmp_path / "study.json").read_text())["pusht"]["blocks"]) == expected


def test_meta_world_tasks_are_prepared_at_once_and_the_rest_follows(es, tmp_path, monkeypatch):
    """--jobs 2: two tasks are built together (a barrier both builds must reach), each gets its
    latency, its student's choice and its headline blocks; every other block of the grid comes
    after all of them, each once."""
    import threading

    study = es.Study(tmp_path, jobs=2)
    together = threading.Barrier(2, timeout=10)
    calls = []

    def build(study_, task):
        together.wait()  # raises BrokenBarrierError if the tasks were built one at a time
        return tmp_path / task

    def latency(key, ws, rows):
        with study.lock:
            study.state.setdefault(key, {})["latency"] = {"decisions": []}

    def choose(key, ws, env, rows, n_val):
        with study.lock:
            study.state[key]["choices"] = {"sefa": choice(
                "receding K=2", {"mode": "receding", "replan_every": 2, "samples": 1})}

    def run_block(key, ws, env, row, spec, first, n):
        with study.lock:
            calls.append((key, row.slug, spec))
            study.record(key, f"{row.slug}|{spec}|{first}", block(key, [1.0] * n))

    monkeypatch.setattr(es, "build_metaworld", build)
    monkeypatch.setattr(study, "latency", latency)
    monkeypatch.setattr(study, "choose", choose)
    monkeypatch.setattr(study, "run_block", run_block)
    args = type("Args", (), {"tasks": ["reach", "push"], "n_one_step": 2, "n_multi_step": 2,
                             "block": 2, "skip": None, "n_val": 2})()
    es.metaworld(study, args)
    headline = {(f"metaworld:{t}", row, spec) for t in ("reach", "push") for row, spec in (
        ("sefa", "receding-2"), ("sefa", "receding-8"), ("base_rk45", "receding-8"))}
    assert set(calls[:6]) == headline
    grid = sum(len(specs) for specs in es.META_GRID.values())
    assert len(calls) == len(set(calls)) == 2 * grid


def test_task_builders_keep_each_others_records(es, tmp_path):
    """Two tasks' builders, made before either saved, each save their own record: the file
    keeps both (a builder's save would otherwise write back the whole file it read)."""
    reach, push = es.TaskBuilder(tmp_path, "reach"), es.TaskBuilder(tmp_path, "push")
    reach.results["reach"] = {"rows": {}, "demos": 10}
    push.results["push"] = {"rows": {}, "demos": 12}
    reach.save()
    push.save()
    on_disk = es.json.loads((tmp_path / "results.json").read_text())
    assert on_disk == {"reach": {"rows": {}, "demos": 10}, "push": {"rows": {}, "demos": 12}}


def test_latency_is_found_whether_bench_reports_names_or_resolved_paths(es):
    """Newer `sefa bench latency` reports a workspace's targets as resolved paths: the study
    finds them as it finds the bare names, for the real-time column and the block costs."""
    def entry(prefix):
        return {"latency": {"decisions": [
            {"target": f"{prefix}distill", "samples": 16, "p50_ms": 2.0, "p99_ms": 3.0},
            {"target": f"{prefix}train@rk45", "samples": 1, "p50_ms": 80.0, "p99_ms": 90.0},
            {"target": f"{prefix}train@euler-1", "samples": 16, "p50_ms": 1.0, "p99_ms": 1.5}]}}

    for prefix in ("", "/runs/metaworld/reach/"):
        e = entry(prefix)
        assert es.real_time(e, es.ROWS[1], "receding-8", 100.0) is True
        assert es.real_time(e, es.ROWS[1], "receding-8", 12.5) is False
        assert es.real_time(e, es.ROWS[0], "bid-1x16", 4.0) is False  # 3.0 + the weak 1.5
        assert es.real_time(e, es.ROWS[0], "bid-1x16", 5.0) is True
        study = es.Study(Path("/nonexistent"))
        study.state["k"] = {"blocks": {}}
        todo = study.blocks("k", Path("ws"), "k", es.ROWS[:2], {False: 50, True: 50}, 50, set(),
                            e["latency"], 500, {"sefa": ("coherent-1x16",),
                                                "base_rk45": ("receding-8",)})
        costs = {(b[1].slug, b[2]): b[0] for b in todo}
        assert costs[("sefa", "coherent-1x16")] == pytest.approx(50 * 500 * 2.0)
        assert costs[("base_rk45", "receding-8")] == pytest.approx(50 * 500 / 8 * 80.0)
