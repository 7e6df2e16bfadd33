"""A kill -9 or a Ctrl-C at each commit point of reflow, align and distill leaves the workspace
as it was or resumable, never a mix: the stage's pointer names its old run (byte for byte) or
the new run complete, nothing else changed, and the same command then finishes with nothing
left behind. The points (SEFA_FAULT=<point>, sefa_data.store.journal.fault_point):
`stage.written` (the run's manifest is written, the run not renamed into place),
`stage.renamed` (in place, the pointer not moved), `stage.pointed` (pointed at), and inside the
stages `reflow.block` (a block of couplings kept) and `train.checkpointed` (the student's
checkpoint). `sefa collect`'s own points are tested in tests/sefa_sim_tests/test_collect_file.py.

The workspace: the catalogue's tiny one (tests/artifact_bad_inputs.py: Push-T low-dim from
../shared/data, a 32x32 MLP flow), its couplings solved with Euler steps so that a rerun takes
seconds; each case runs a command with new settings (a new run) on a copy of it. A kill -9 needs
a child process; a Ctrl-C is sent in-process (tests/cli_inprocess.py).
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from artifact_bad_inputs import have_shared, make_workspace, snapshot
from cli_inprocess import run_cli

REPO = Path(__file__).resolve().parents[2]
# a command per stage with new settings, so that it makes a new run; the stage's pointer
COMMANDS = {"reflow": (["reflow", "--samples", "3"], "reflow/iter_1"),
            "align": (["align", "--eps", "0.2"], "align"),
            "distill": (["distill", "--train-steps", "20"], "distill")}
POINTS = ["stage.written", "stage.renamed", "stage.pointed"]
INSIDE = [("reflow", "reflow.block"), ("distill", "train.checkpointed")]
LEFTOVER = (".partial", ".old-", ".link-", ".tmp-", ".copy")


def sefa(ws: Path, *args, env: dict | None = None) -> tuple[int, str, str]:
    """`sefa ARGS -w WS` in this process, with `env` (SEFA_FAULT) set while it runs."""
    from sefa_data.store import journal

    saved = dict(os.environ)
    journal._reached.clear()  # fault points count per command
    os.environ.pop("SEFA_FAULT", None)
    os.environ.update(env or {})
    try:
        r = run_cli(*args, "-w", ws, threads=1)
    finally:
        os.environ.clear()
        os.environ.update(saved)
    return r.returncode, r.stdout, r.stderr


@pytest.fixture(scope="module")
def template(tmp_path_factory) -> Path:
    if not have_shared():
        pytest.skip("the tiny workspace is built from ../shared/data (absent here)")
    ws = make_workspace(tmp_path_factory.mktemp("commit"))
    for args in (["config", "set", "reflow.solver", "euler"],
                 ["config", "set", "distill.train_overrides",
                  "[training.checkpoint_every=5]"], ["distill", "--yes"]):
        code, _, err = sefa(ws, *args)
        assert code == 0, err
    return ws


def _copy(template: Path, tmp_path: Path) -> Path:
    ws = tmp_path / "ws"
    shutil.copytree(template, ws, symlinks=True)
    return ws


def _leftovers(ws: Path) -> list[str]:
    return sorted(str(p.relative_to(ws)) for p in ws.rglob(".*")
                  if any(mark in p.name for mark in LEFTOVER))


def _check_old_or_new(ws: Path, before: dict, link: str, resumable: bool) -> str:
    """'old' (every file as it was but the stage's new run folder or partial, and .sefa/) or
    'new' (the pointer names a complete new run, nothing else moved)."""
    after = snapshot(ws)
    target = os.readlink(ws / link)
    moved = sorted(k for k in before.keys() | after.keys() if before.get(k) != after.get(k)
                   and not k.startswith(".sefa/") and not k.startswith(f"runs/{link}/")
                   and k != link)
    assert not moved, f"changed outside the stage's runs: {moved[:8]}"
    old = before[link].decode().removeprefix("-> ")
    if target == old:
        run = old.split("/")[-1]
        assert {k: v for k, v in after.items() if k.startswith(f"runs/{link}/{run}/")} == \
               {k: v for k, v in before.items() if k.startswith(f"runs/{link}/{run}/")}
        partials = list((ws / "runs" / link).glob(".*.partial"))
        # a partial is kept only to be continued (a killed process cleans nothing: the next
        # command removes what it left)
        assert not partials or resumable, partials
        return "old"
    assert (ws / link / "manifest.json").is_file() and not (ws / link).name.startswith(".")
    return "new"


def _resumable(stage: str, point: str) -> bool:
    """Whether the run's folder is kept to be continued: a training's (it holds a checkpoint)
    or reflow's before its couplings are written (its blocks)."""
    return stage == "distill" or point == "reflow.block"


def _kill_at(ws: Path, args: list, point: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1",
           "SEFA_FAULT": point}
    return subprocess.run([sys.executable, "-m", "sefa_cli.main", *args, "-w", str(ws)],
                          env=env, capture_output=True, text=True, timeout=300)


def _finishes(ws: Path, args: list, link: str) -> None:
    code, _, err = sefa(ws, *args)
    assert code == 0, err
    assert _leftovers(ws) == []
    code, out, err = sefa(ws, *args)  # the same again: nothing to do
    assert code == 0 and "running" not in err, err
    assert (ws / link / "manifest.json").is_file()


@pytest.mark.parametrize("stage,point", [(s, p) for s in COMMANDS for p in POINTS] + INSIDE)
def test_kill_9_at_a_commit_point_leaves_the_old_state_or_a_resumable_one(template, tmp_path,
                                                                           stage, point) -> None:
    args, link = COMMANDS[stage]
    ws = _copy(template, tmp_path)
    before = snapshot(ws)
    r = _kill_at(ws, args, point)
    assert r.returncode == -signal.SIGKILL, r.stderr[-2000:]
    state = _check_old_or_new(ws, before, link, resumable=True)
    assert state == ("new" if point == "stage.pointed" else "old")
    _finishes(ws, args, link)


@pytest.mark.parametrize("stage,point", [(s, p) for s in COMMANDS for p in POINTS] + INSIDE)
def test_ctrl_c_at_a_commit_point_says_which_state_it_left(template, tmp_path, stage,
                                                           point) -> None:
    args, link = COMMANDS[stage]
    ws = _copy(template, tmp_path)
    before = snapshot(ws)
    code, _, err = sefa(ws, *args, env={"SEFA_FAULT": f"{point}:sigint"})
    assert code == 130, err
    line = err.strip().splitlines()[-1]
    state = _check_old_or_new(ws, before, link, resumable=_resumable(stage, point))
    if point == "stage.pointed":
        assert state == "new" and line.startswith(f"interrupted after {link.split('/')[0]}")
        assert line.endswith("is complete"), line
    elif point == "stage.renamed":
        assert state == "old" and line.startswith(f"interrupted: {link} is as it was; its new "
                                                  "run runs/"), line
    elif point == "stage.written" and not _resumable(stage, point):
        assert state == "old" and line == ("interrupted: stores and artifacts are as they were "
                                           "before this stage"), line
    else:  # inside the stage: what was kept, and how to continue
        assert state == "old" and line.startswith("interrupted: kept runs/"), line
    _finishes(ws, args, link)
