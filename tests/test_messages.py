"""What `sefa` says when a run is interrupted, resumed, running or blocked (issue 25, traps 5, 6
and 9), through `cli.main.main` in-process on a three-episode Push-T store. A Ctrl-C is fault
injection (SEFA_FAULT=train.checkpointed:sigint:N: the process sends itself SIGINT right after
its Nth checkpoint), never timing luck."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from test_interrupts import small_store

TINY = ["policy.head=mlp", "policy.mlp_hidden_dims=[32,32]", "policy.time_embed_dim=16",
        "training.max_steps=40", "training.batch_size=16", "training.val_every=20",
        "training.checkpoint_every=10", "training.val_batches=1",
        "training.val_sample_windows=4", "training.log_every=5", "flow.solver=euler",
        "flow.steps=2"]


def sefa(monkeypatch, capsys, ws: Path, *args, env: dict | None = None) -> tuple[int, str, str]:
    """(exit code, stdout, stderr) of `sefa ARGS -w WS`, run in this process."""
    from cli.main import main
    from sefa_data import store_journal

    monkeypatch.setattr("sys.argv", ["sefa", *map(str, args), "-w", str(ws)])
    monkeypatch.setattr(store_journal, "_reached", {})  # fault points count per command
    monkeypatch.delenv("SEFA_FAULT", raising=False)
    for k, v in (env or {}).items():
        monkeypatch.setenv(k, v)
    capsys.readouterr()
    try:
        main()
        code = 0
    except SystemExit as e:
        code = e.code or 0
    finally:
        monkeypatch.delenv("SEFA_FAULT", raising=False)
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture(scope="module")
def store(shared_data, tmp_path_factory) -> Path:
    from sefa_data.ingest import IngestOptions, ingest

    tmp = tmp_path_factory.mktemp("msgs")
    out = tmp / "dataset.zarr"
    ingest([small_store(tmp / "a.zarr", shared_data, 0, 3)], out, IngestOptions(fps=10))
    return out


@pytest.fixture
def ws(store, tmp_path) -> Path:
    ws = tmp_path / "ws"
    ws.mkdir()
    shutil.copytree(store, ws / "dataset.zarr")
    return ws


def _tensorboard_steps(run: Path) -> list[int]:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(run / "tensorboard"))
    events.Reload()
    return [e.step for e in events.Scalars("train/loss")]


def test_ctrl_c_says_what_was_kept_and_resume_makes_one_whole_run(ws, monkeypatch, capsys):
    # Ctrl-C right after the checkpoint at step 20 of 40 (the second one)
    code, _, err = sefa(monkeypatch, capsys, ws, "train", *TINY,
                        env={"SEFA_FAULT": "train.checkpointed:sigint:2"})
    assert code == 130, err
    (partial,) = ws.glob("runs/train/.*.partial")
    rel = partial.relative_to(ws).as_posix()
    assert err.strip().splitlines()[-1] == (
        f"interrupted: kept {rel} at step 20 of 40 (not a complete artifact); continue with "
        "`sefa train` (it resumes), or `sefa train --force` to start over")
    assert "as they were before" not in err and "Traceback" not in err

    # status names the kept run and the command that continues it
    code, out, _ = sefa(monkeypatch, capsys, ws, "status", "--json")
    view = json.loads(out)
    train = next(r for r in view["rows"] if r["stage"] == "train")
    assert f"interrupted run kept: {rel} at step 20 of 40, `sefa train` continues it" in \
        train["reason"]
    assert view["next"] == f"sefa train (continues the interrupted run: {rel} at step 20 of 40)"
    first = json.loads((partial / ".sefa-segments.json").read_text())["durations_s"]

    code, _, err = sefa(monkeypatch, capsys, ws, "train")
    assert code == 0 and "resuming" in err and "at step 20" in err, err
    run = ws / "runs/train" / partial.name[1:].removesuffix(".partial")
    manifest = json.loads((run / "manifest.json").read_text())
    # the run's time is both segments', and its id is its folder's
    assert manifest["segments_s"][0] == first[0] and len(manifest["segments_s"]) == 2
    assert manifest["duration_s"] == pytest.approx(sum(manifest["segments_s"]), abs=1e-3)
    assert manifest["duration_s"] > first[0]
    assert manifest["run_id"] == run.name and len(manifest["build_id"]) == 32
    assert not (run / ".sefa-segments.json").exists()
    # TensorBoard holds every logged step once, the checkpoint's (20) included, as logs.jsonl
    logged = [json.loads(line)["step"] for line in (run / "logs.jsonl").read_text().splitlines()
              if "train_loss" in line]
    assert logged == [5, 10, 15, 20, 25, 30, 35, 40]
    assert _tensorboard_steps(run) == logged


def test_curves_are_titled_by_the_run_id_not_its_build_folder():
    from sefa_model.run_log import run_name

    assert run_name(Path("runs/train/.8b7bcb193bb3.partial")) == "8b7bcb193bb3"
    assert run_name(Path("runs/train/8b7bcb193bb3")) == "8b7bcb193bb3"


def test_ctrl_c_in_a_tee_pipeline_still_exits_130_and_keeps_the_run(ws):
    """A terminal's Ctrl-C reaches every process of `sefa train 2>&1 | tee LOG`
    (SEFA_FAULT=...:sigint-group sends it to the process group, as a terminal does): tee dies
    first, and sefa, its stderr gone, still exits 130 with its checkpoint kept (it exited 1).
    The log then ends early; README's `tee -i` is the fix for that."""
    import os
    import signal
    import subprocess
    import sys

    repo = Path(__file__).resolve().parents[1]
    (ws / "sefa.yaml").write_text(json.dumps({"train": TINY}))  # YAML reads JSON
    log = ws / "train.log"
    script = (f"{sys.executable} -m cli.main train -w {ws} 2>&1 | tee {log}; "
              f"echo ${{PIPESTATUS[0]}} > {ws / 'rc'}")
    subprocess.run(["bash", "-c", script], cwd=repo, start_new_session=True, timeout=300,
                   env={**os.environ, "PYTHONPATH": str(repo), "OMP_NUM_THREADS": "1",
                        "SEFA_FAULT": "train.checkpointed:sigint-group:2"},
                   preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    assert (ws / "rc").read_text().strip() == "130", log.read_text()[-2000:]
    assert len(list(ws.glob("runs/train/.*.partial/checkpoints/latest"))) == 1
    assert "validation at step 20/40" in log.read_text()  # it ran to the interrupt
