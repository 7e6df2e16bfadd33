"""What `sefa` says when a run is interrupted, resumed, running or blocked (issue 25, traps 5, 6
and 9), through `sefa_cli.main.main` in-process on a three-episode Push-T store. A Ctrl-C is fault
injection (SEFA_FAULT=train.checkpointed:sigint:N: the process sends itself SIGINT right after
its Nth checkpoint), never timing luck."""

from __future__ import annotations

import signal

import json
import os
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from test_interrupts import small_store

TINY = ["policy.head=mlp", "policy.mlp_hidden_dims=[32,32]", "policy.time_embed_dim=16",
        "training.max_steps=40", "training.batch_size=16", "training.val_every=20",
        "training.checkpoint_every=10", "training.val_batches=1",
        "training.val_sample_windows=4", "training.log_every=5", "flow.solver=euler",
        "flow.steps=2"]


def sefa(ws: Path, *args, env: dict | None = None) -> tuple[int, str, str]:
    """(exit code, stdout, stderr) of `sefa ARGS -w WS`, run in this process (usable from a
    module fixture, hence no monkeypatch/capsys)."""
    import contextlib
    import io
    import os
    import sys

    from sefa_cli.main import main
    from sefa_data.store import journal as store_journal

    out, err = io.StringIO(), io.StringIO()
    saved_argv, saved_env = sys.argv, dict(os.environ)
    sys.argv = ["sefa", *map(str, args), "-w", str(ws)]
    store_journal._reached.clear()  # fault points count per command
    os.environ.pop("SEFA_FAULT", None)
    os.environ.update(env or {})
    # as a fresh process has it: an earlier in-process command (a server's signal handlers) may
    # have left another SIGINT handler, and then a fault's SIGINT would interrupt nothing
    saved_sigint = signal.signal(signal.SIGINT, signal.default_int_handler)
    code = 0
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            main()
    except SystemExit as e:
        code = e.code or 0
    finally:
        sys.argv = saved_argv
        os.environ.clear()
        os.environ.update(saved_env)
        signal.signal(signal.SIGINT, saved_sigint)
    return code, out.getvalue(), err.getvalue()


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


def test_ctrl_c_says_what_was_kept_and_resume_makes_one_whole_run(ws):
    # Ctrl-C right after the checkpoint at step 20 of 40 (the second one)
    code, _, err = sefa(ws, "train", *TINY,
                        env={"SEFA_FAULT": "train.checkpointed:sigint:2"})
    assert code == 130, err
    (partial,) = ws.glob("runs/train/.*.partial")
    rel = partial.relative_to(ws).as_posix()
    assert err.strip().splitlines()[-1] == (
        f"interrupted: kept {rel} at step 20 of 40 (not a complete artifact); continue with "
        "`sefa train` (it resumes), or `sefa train --force` to start over")
    assert "as they were before" not in err and "Traceback" not in err

    # status names the kept run and the command that continues it
    code, out, _ = sefa(ws, "status", "--json")
    view = json.loads(out)
    train = next(r for r in view["rows"] if r["stage"] == "train")
    assert f"interrupted run kept: {rel} at step 20 of 40, `sefa train` continues it" in \
        train["reason"]
    assert view["next"] == f"sefa train (continues the interrupted run: {rel} at step 20 of 40)"
    first = json.loads((partial / ".sefa-segments.json").read_text())["durations_s"]

    code, _, err = sefa(ws, "train")
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
    from sefa_model.train.run_log import run_name

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

    repo = Path(__file__).resolve().parents[2]
    (ws / "sefa.yaml").write_text(json.dumps({"train": TINY}))  # YAML reads JSON
    log = ws / "train.log"
    script = (f"{sys.executable} -m sefa_cli.main train -w {ws} 2>&1 | tee {log}; "
              f"echo ${{PIPESTATUS[0]}} > {ws / 'rc'}")
    subprocess.run(["bash", "-c", script], cwd=repo, start_new_session=True, timeout=300,
                   env={**os.environ, "PYTHONPATH": str(repo), "OMP_NUM_THREADS": "1",
                        "SEFA_FAULT": "train.checkpointed:sigint-group:2"},
                   preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    assert (ws / "rc").read_text().strip() == "130", log.read_text()[-2000:]
    assert len(list(ws.glob("runs/train/.*.partial/checkpoints/latest"))) == 1
    assert "validation at step 20/40" in log.read_text()  # it ran to the interrupt


@pytest.fixture(scope="module")
def trained(store, tmp_path_factory) -> tuple[Path, str]:
    """A workspace whose base flow is trained (TINY), and what the training printed."""
    ws = tmp_path_factory.mktemp("trained") / "ws"
    ws.mkdir()
    shutil.copytree(store, ws / "dataset.zarr")
    # a busy machine, as the load average says (TINY trains with 2 threads)
    busy, os.getloadavg = os.getloadavg, lambda: (6.0, 6.0, 6.0)
    try:
        code, _, err = sefa(ws, "train", *TINY, "--threads", "2")
    finally:
        os.getloadavg = busy
    assert code == 0, err
    return ws, err


def test_a_busy_machine_is_said_when_training_starts(trained):
    _, err = trained
    assert f"the machine is busy (load 6.0 on {os.cpu_count()} cores) and torch uses 2 threads: " \
           "`--threads 1`" in err or os.cpu_count() > 6


def test_piped_progress_says_when_the_loss_was_measured(trained):
    """The loss is read at log steps (every 5 here); the lines between say which step's it is,
    instead of repeating it as if new."""
    _, err = trained
    lines = [line for line in err.splitlines() if line.startswith("train ")]
    assert any(line.startswith("train 6/40 (15%) loss ") and "(at step 5) |" in line
               for line in lines), lines
    assert all("(at step" not in line for line in lines if line.startswith(("train 10/", "train 20/")))


def test_a_finished_offline_solve_ends_at_its_end(trained):
    """A one-step solve's only network call starts at t = 0: it ended at 0/1000."""
    ws, _ = trained
    code, _, err = sefa(ws, "eval", "--offline", "--solver", "euler", "--steps", "1",
                        "--windows", "4", "--samples", "2")
    assert code == 0, err
    last = [line for line in err.splitlines() if line.startswith("offline eval ")][-1]
    assert last.startswith("offline eval 1000/1000 (100%) NFE 1 chunks 8"), err


def test_results_show_rollout_nfe_and_whole_folder_names(trained, monkeypatch):
    """On an 80-column terminal too: the folder names are what the next command needs."""
    import sefa_cli.console

    monkeypatch.setattr(sefa_cli.console.out, "width", 80)
    ws, _ = trained
    code, _, err = sefa(ws, "eval", "--env", "pusht", "--n-test", "1", "--max-steps", "8")
    assert code == 0, err
    log = json.loads(next((ws / "evals").glob("pusht-*/eval_log.json")).read_text())
    assert log["nfe"] == 2  # TINY's flow: euler, 2 steps
    folder = next(p for p in (ws / "evals").iterdir() if p.name.startswith("pusht-"))
    run = (ws / "train").resolve().name
    code, out, _ = sefa(ws, "results")
    assert (f"evals/{folder.name}  train (runs/train/{run})  base_flow, pusht, euler-2, "
            "receding K=8, NFE 2\n") in out, out
    monkeypatch.setattr(sefa_cli.console.out, "width", 160)  # wide enough: the table
    code, out, _ = sefa(ws, "results")
    row = next(line for line in out.splitlines() if "│ pusht " in line)
    cells = [c.strip() for c in row.split("│")][1:-1]
    assert cells[:6] == [f"train (runs/train/{run})", "base_flow", "pusht", "euler-2",
                         "receding K=8", "2"]
    assert cells[-1] == f"evals/{folder.name}"  # the result cell wraps, names do not


def test_status_during_a_run_shows_no_numbers_of_the_old_run(trained):
    """While a new training of other settings runs, its row is `running` with the build folder,
    and the current run's metric and duration are not shown beside it."""
    import yaml

    from sefa_pipelines.overview import _settings
    from sefa_pipelines.runner import Workspace, run_id
    from sefa_pipelines.stages import stages

    ws, _ = trained
    flags = ws / ".sefa" / "flags.yaml"
    before = flags.read_text()
    try:
        flags.write_text(yaml.safe_dump({"train": TINY + ["training.max_steps=60"]}))
        pipe, _, _ = _settings(ws)
        train = stages(ws, pipe)[0]
        w = Workspace(ws)
        partial = w.partial_dir(train.artifact, run_id(train, w.input_fingerprints(train)))
        partial.mkdir(parents=True)
        with w.lock():  # as the running training holds it
            code, out, _ = sefa(ws, "status", "--json")
    finally:
        flags.write_text(before)
        shutil.rmtree(partial, ignore_errors=True)
    row = next(r for r in json.loads(out)["rows"] if r["stage"] == "train")
    assert row["state"] == "running" and row["path"] == partial.relative_to(ws).as_posix()
    assert row["metric"] is None and row["duration"] is None


def test_status_suggests_only_a_simulator_that_gives_the_observations(store, shared_data,
                                                                      tmp_path):
    """For a store whose keys no simulator provides (KUKA's), no `--env pusht`."""
    from sefa_pipelines.evals import rollout_envs
    from sefa_pipelines.overview import _settings, eval_hint
    from sefa_data.ingest import IngestOptions, ingest

    assert rollout_envs(["keypoint", "state"]) == ["pusht"]
    assert rollout_envs(["observation.state"]) == []  # KUKA's name is not Push-T's `state`
    assert rollout_envs(["observation.robot0_eef_pos", "observation.object"]) == ["robosuite:Lift"]
    ws = tmp_path / "ws"
    ws.mkdir()
    shutil.copytree(store, ws / "dataset.zarr")
    assert eval_hint(ws, _settings(ws)[0]) == "sefa eval --offline (or --env pusht)"
    kuka = tmp_path / "kuka"
    kuka.mkdir()
    ingest([small_store(tmp_path / "a.zarr", shared_data, 0, 2)], kuka / "dataset.zarr",
           IngestOptions(fps=10, renames={"state": "observation.state"}))
    assert eval_hint(kuka, _settings(kuka)[0]) == "sefa eval --offline"


# --- trap 9: the smaller messages ------------------------------------------------------------


def test_no_store_names_sefa_ingest_and_creates_no_folder(tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    code, _, err = sefa(empty, "distill")
    assert code == 1 and err.strip().splitlines()[-1] == (
        f"error: {empty}/dataset.zarr: no episode store in this workspace: `sefa ingest "
        f"RECORDINGS -w {empty}` makes it, then `sefa distill`")
    assert list(empty.iterdir()) == []
    missing = tmp_path / "nonexistent"
    code, _, err = sefa(missing, "train")
    assert code == 1 and f"(no folder {missing}): `sefa ingest RECORDINGS -w {missing}`" in err
    assert not missing.exists()


def test_a_command_blocked_by_a_running_training_says_so(ws):
    from sefa_pipelines.runner import Workspace

    (ws / "sefa.yaml").write_text(json.dumps({"train": TINY}))
    (ws / "runs" / "train" / ".0123456789ab.partial").mkdir(parents=True)
    with Workspace(ws).lock():  # as the running training holds it
        code, _, err = sefa(ws, "reflow")  # (said `must first run train`)
    assert code == 1 and err.strip().splitlines()[-1] == (
        f"error: train is running (pid {os.getpid()}) in this workspace: `sefa reflow` can start "
        "once it ends (`sefa status` shows it)")


def test_a_store_without_an_action_key_is_said_at_ingest(shared_data, tmp_path):
    src = small_store(tmp_path / "a.zarr", shared_data, 0, 1)
    ws = tmp_path / "ws"
    code, _, err = sefa(ws, "ingest", src, "--fps", "10", "--rename", "action=cmd")
    assert code == 0, err
    assert (f"warning: {ws}/dataset.zarr has no `action` key (it has cmd, state): `sefa train` "
            "trains on `action`") in err


def test_a_warmup_longer_than_the_run_is_said_naming_both(ws):
    """The default warmup (500 steps) with a 20-step run: the learning rate never reaches
    training.lr; a warmup shorter than the run says nothing."""
    short = [*TINY, "training.max_steps=20", "training.checkpoint_every=20"]
    code, _, err = sefa(ws, "train", *short, "--out", ws / "runa")
    assert code == 0, err
    assert ("warning: training.lr_warmup_steps (500) is not shorter than training.max_steps "
            "(20): the learning rate never reaches training.lr (0.0001)") in err, err
    # the cost, before the first step (estimated: a whole batch of 16 is cheap to time) and
    # past the warm-up (measured: a tenth of the run, its first step left out), in that order
    lines = err.splitlines()
    cost = next(i for i, line in enumerate(lines) if line.startswith("cost: 20 steps of batch 16, about "))
    measured = next(i for i, line in enumerate(lines) if line.startswith("measured: "))
    # timed several times, or once where one call took the whole timing budget (a busy machine)
    timed = re.search(r"\(a batch of 16 timed( (\d+) times)?\), ETA about 0:\d\d$", lines[cost])
    assert timed, err
    assert int(timed.group(2) or 1) <= 20, err  # a probe no longer than the run's own steps
    assert cost < measured, err
    assert "over steps 2-3 (step 1 left out: warm-up), ETA about" in lines[measured], err
    assert "a CPU-sized run" not in lines[cost]  # seconds, not hours
    code, _, err = sefa(ws, "train", *short, "training.lr_warmup_steps=5", "--out", ws / "runb")
    assert code == 0 and "warning: training.lr_warmup_steps" not in err, err


def test_an_all_constant_action_is_said_at_ingest(shared_data, tmp_path):
    """Two real Push-T episodes whose action is overwritten with one value (written with zarr):
    ingest keeps it, and says a policy cannot learn from it; a real action says nothing."""
    import zarr

    src = small_store(tmp_path / "a.zarr", shared_data, 0, 2)
    root = zarr.open_group(str(src), mode="r+")
    n = root["data/action"].shape[0]
    root["data/action"][:] = np.tile(np.array([[256.0, 100.0]], np.float32), (n, 1))
    ws = tmp_path / "ws"
    code, _, err = sefa(ws, "ingest", src, "--fps", "10")
    assert code == 0, err
    assert (f"warning: {ws}/dataset.zarr: `action` is constant (256, 100 in all {n} frames): a "
            "policy trained on it cannot learn anything") in err, err
    real = small_store(tmp_path / "b.zarr", shared_data, 0, 2)
    code, _, err = sefa(tmp_path / "ws2", "ingest", real, "--fps", "10")
    assert code == 0 and "warning" not in err, err


def test_the_ros_scaffold_says_it_names_no_action(shared_data):
    from sefa_data.readers.ros import scaffold_topic_map

    text = scaffold_topic_map(shared_data / "kuka_lwr_honeypot_joint_states.bag")
    assert "# TODO: no feature is named `action`, the key `sefa train` trains on" in text


def test_inspect_prints_one_row_per_dimension(ws, monkeypatch):
    import sefa_cli.console

    monkeypatch.setattr(sefa_cli.console.out, "width", 80)
    code, out, _ = sefa(ws, "inspect")
    assert code == 0
    rows = [[c.strip() for c in line.split("│")[1:-1]] for line in out.splitlines()
            if line.startswith("│") and len(line.split("│")) == 10]
    state = json.loads(sefa(ws, "inspect", "--json")[1])["features"]["state"]["stats"]
    assert [r[:2] for r in rows] == [["action", "0"], ["", "1"], ["state", "0"]] + \
        [["", str(d)] for d in range(1, 5)]
    assert rows[6][2:] == [f"{state[s][4]:.4g}" for s in ("min", "max", "mean", "std", "q01", "q99")]


def test_a_busy_machine_suggests_one_thread():
    import torch

    from sefa_model.distributed import busy_cpu_note

    cpu = torch.device("cpu")
    assert busy_cpu_note(cpu, 2, 5.3, 2) == (
        "the machine is busy (load 5.3 on 2 cores) and torch uses 2 threads: `--threads 1` "
        "(or `threads: 1` in sefa.yaml) is often much faster here")
    assert busy_cpu_note(cpu, 2, 0.4, 2) is None  # a quiet machine
    assert busy_cpu_note(cpu, 1, 5.3, 2) is None  # already one thread
    assert busy_cpu_note(torch.device("meta"), 2, 5.3, 2) is None  # not a CPU run


def test_a_second_ingest_into_a_store_being_created_names_the_other_process(shared_data,
                                                                             tmp_path):
    """Another `sefa ingest` is creating the store (its temporary store, named by its pid, is
    locked): this one says so, and leaves that store alone (it deleted it, and the first ingest
    then failed on `No such file or directory (.dataset.zarr.tmp-N/.sefa-journal)`)."""
    import subprocess
    import sys

    ws = tmp_path / "ws"
    ws.mkdir()
    other = subprocess.Popen(
        [sys.executable, "-c", "import fcntl, os, sys, time\n"
         "d = os.path.join(sys.argv[1], f'.dataset.zarr.tmp-{os.getpid()}')\n"
         "os.mkdir(d); fcntl.flock(os.open(d, os.O_RDONLY), fcntl.LOCK_EX)\n"
         "print(d, flush=True); time.sleep(120)", str(ws)],
        stdout=subprocess.PIPE, text=True)
    try:
        building = Path(other.stdout.readline().strip())
        src = small_store(tmp_path / "a.zarr", shared_data, 0, 1)
        code, _, err = sefa(ws, "ingest", src, "--fps", "10")
        assert code == 1 and err.strip().splitlines()[-1] == (
            f"error: {ws}/dataset.zarr: another process (pid {other.pid}) is creating this "
            "store; run this ingest again once it has finished (it then appends)")
        assert building.is_dir() and not (ws / "dataset.zarr").exists()
    finally:
        other.kill()
        other.wait()


def test_a_refused_command_prints_its_error_alone(ws):
    """No preamble: the machine's default head is said when the base policy trains (and the
    refusal names it), not before every command."""
    (ws / "sefa.yaml").write_text(json.dumps({"train": ["training.batch_size=16"]}))  # no head
    code, _, err = sefa(ws, "align")
    assert code == 1 and len(err.strip().splitlines()) == 1, err
    assert err.startswith("error: `sefa align` must first run train (no complete artifact at "
                          "train/): trains the base policy (")


def test_ctrl_c_in_reflow_keeps_its_finished_blocks_and_the_next_run_reuses_them(ws, tmp_path):
    """Ctrl-C right after reflow's 2nd of 5 blocks (fault injection, SEFA_FAULT=reflow.block:
    sigint:2): the build folder keeps both blocks and says so; the same command solves only the
    other 3 (the fault point counts the blocks a run solves) and writes couplings identical to
    an uninterrupted run's."""
    import zarr

    code, _, err = sefa(ws, "train", *TINY)
    assert code == 0, err
    clean = tmp_path / "clean"
    shutil.copytree(ws, clean, symlinks=True)
    args = ("reflow", "--max-windows", "40", "--samples", "2", "--block-windows", "8")
    code, _, err = sefa(ws, *args, env={"SEFA_FAULT": "reflow.block:sigint:2"})
    assert code == 130, err
    (partial,) = ws.glob("runs/reflow/iter_1/.*.partial")
    rel = partial.relative_to(ws).as_posix()
    assert sorted(p.name for p in (partial / "couplings.blocks").glob("block_*")) == [
        "block_000000000.npz", "block_000000008.npz"]
    assert err.strip().splitlines()[-1].startswith(
        f"interrupted: kept {rel} with 2 finished blocks of couplings"), err

    from sefa_data.store import journal as store_journal

    code, _, err = sefa(ws, *args, env={"SEFA_FAULT": "reflow.block:sigint:1000"})
    assert code == 0, err
    assert "reusing 2 of 5 blocks of couplings kept by an interrupted run (16 windows)" in err, err
    assert store_journal._reached["reflow.block"] == 3  # the kept two were not solved again
    code, _, err = sefa(clean, *args)
    assert code == 0, err
    got = zarr.open_group(str(ws / "reflow/iter_1/couplings.zarr"), mode="r")
    want = zarr.open_group(str(clean / "reflow/iter_1/couplings.zarr"), mode="r")
    for key in ("noise", "action", "window"):
        np.testing.assert_array_equal(got[key][:], want[key][:])
    assert not list(ws.glob("runs/reflow/iter_1/*/couplings.blocks"))  # gone once written
