"""`sefa convert` never loses a user's file, never hangs, and leaves nothing behind (issue 33):

- publishing never replaces anything: a folder that appears at --out while the conversion runs
  is left as it is (fault injection: made between the start's check and the final rename);
- the video encoder runs in a child process under a watchdog: a simulated SVT-AV1 hang (the
  fault point ``convert.encode:hang`` sleeps for ever inside the encoder's process) is stopped
  within its timeout, and Ctrl-C and SIGTERM stop it at once;
- temporary names carry the owner's pid (``.OUT.store-PID``, ``.OUT.tmp-PID``): after a kill -9
  at each fault point, the next run removes them;
- every input, the task strings and odd --out targets are checked before any input is read,
  each as one line naming the user's own path.

The inputs are small LeRobot v2.1 datasets written by the real writers (pyarrow, PyAV: see
tests/sefa_data_tests/test_lerobot.py's `write_v21`). Most cases run the CLI in-process (tests/cli_inprocess.py);
signals and kill -9 need a real child process.
"""

from __future__ import annotations

import json
import multiprocessing
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from cli_inprocess import run_cli
from test_lerobot import write_v21

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture
def v21(tmp_path) -> Path:
    write_v21(tmp_path / "v21", lengths=(6, 5))
    return tmp_path / "v21"


def sefa(tmp_path: Path, *args) -> subprocess.CompletedProcess:
    return run_cli(*args, cwd=tmp_path)


def child(tmp_path: Path, *args, fault: str | None = None, **popen) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    env.pop("SEFA_FAULT", None)
    if fault:
        env["SEFA_FAULT"] = fault
    # a suite started in the background by a shell ignores SIGINT, and a child inherits that:
    # the child gets the default dispositions back, as a command started from a terminal has
    popen.setdefault("preexec_fn", default_signals)
    return subprocess.Popen([sys.executable, "-m", "sefa_cli.main", *map(str, args)], cwd=tmp_path,
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            **popen)


def default_signals() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


def one_error(r: subprocess.CompletedProcess, *fragments: str) -> str:
    assert r.returncode == 1, (r.stdout, r.stderr)
    assert "Traceback" not in r.stderr
    errors = [l for l in r.stderr.splitlines() if l.startswith("error:")]
    assert len(errors) == 1, r.stderr
    for f in fragments:
        assert f in errors[0], errors[0]
    return errors[0]


def debris(tmp_path: Path) -> list[str]:
    return sorted(p.name for p in tmp_path.iterdir() if p.name.startswith("."))


def tree(path: Path) -> dict[str, bytes]:
    return {str(p.relative_to(path)): p.read_bytes() for p in sorted(path.rglob("*"))
            if p.is_file()}


def test_a_folder_that_appears_during_the_conversion_is_left_as_it_is(v21, tmp_path, monkeypatch):
    """The race: --out is free at the start, someone makes it (with a file in it) while the
    dataset is written; the final rename must refuse, not move it aside and delete it."""
    from sefa_data.lerobot import writer as lerobot_writer

    out = tmp_path / "out"
    real = lerobot_writer._Writer._write_meta
    theirs = {"theirs.txt": b"a user's file"}

    def meanwhile(self, frames):  # the last step before the rename
        real(self, frames)
        out.mkdir()
        for name, data in theirs.items():
            (out / name).write_bytes(data)

    monkeypatch.setattr(lerobot_writer._Writer, "_write_meta", meanwhile)
    r = sefa(tmp_path, "convert", v21, "--out", out)
    one_error(r, "out: appeared while the conversion ran; it was left as it is")
    assert tree(out) == {"theirs.txt": b"a user's file"}
    assert debris(tmp_path) == []
    # an empty folder too (a plain rename would have replaced it)
    (out / "theirs.txt").unlink()
    out.rmdir()
    theirs.clear()
    r = sefa(tmp_path, "convert", v21, "--out", out)
    one_error(r, "appeared while the conversion ran")
    assert out.is_dir() and list(out.iterdir()) == [] and debris(tmp_path) == []


def test_publish_new_dir_refuses_every_kind_of_existing_target(tmp_path):
    from sefa_data.atomic import publish_new_dir

    for make in (lambda p: p.mkdir(), lambda p: p.write_text("x"),
                 lambda p: p.symlink_to(tmp_path / "nowhere")):
        src, dst = tmp_path / "src", tmp_path / "dst"
        src.mkdir()
        (src / "a").write_text("new")
        make(dst)
        before = os.lstat(dst)
        with pytest.raises(FileExistsError):
            publish_new_dir(src, dst)
        assert os.lstat(dst).st_ino == before.st_ino and (src / "a").read_text() == "new"
        for p in (src, dst):
            if p.is_dir() and not p.is_symlink():
                (p / "a").unlink(missing_ok=True)
                p.rmdir()
            else:
                p.unlink()
    (tmp_path / "src").mkdir()
    publish_new_dir(tmp_path / "src", tmp_path / "dst")
    assert (tmp_path / "dst").is_dir() and not (tmp_path / "src").exists()


def test_a_hung_encoder_is_stopped_within_its_timeout(v21, tmp_path, monkeypatch):
    monkeypatch.setenv("SEFA_FAULT", "convert.encode:hang")
    start = time.monotonic()
    r = sefa(tmp_path, "convert", v21, "--out", tmp_path / "out", "--encoder-timeout", "2")
    took = time.monotonic() - start
    one_error(r, "observation.images.cam: the av1 encoder stalled on episode 0 (6 frames): "
                 "no frame encoded in 2 s", "--encoder-timeout")
    assert took < 30, took  # 2 s of watchdog, plus the ingest and the encoder's start
    assert not (tmp_path / "out").exists() and debris(tmp_path) == []
    assert multiprocessing.active_children() == []  # the hung encoder was killed


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_ctrl_c_and_sigterm_stop_a_hung_encoder(v21, tmp_path, sig):
    p = child(tmp_path, "convert", v21, "--out", tmp_path / "out", fault="convert.encode:hang")
    build = tmp_path / f".out.tmp-{p.pid}"
    deadline = time.monotonic() + 60
    while not build.exists() and p.poll() is None and time.monotonic() < deadline:
        time.sleep(0.1)
    time.sleep(2)  # the encoder's process starts and hangs on its first frame
    p.send_signal(sig)
    out, err = p.communicate(timeout=30)
    assert p.returncode == 130, err
    assert "interrupted: nothing was written (" in err and "Traceback" not in err
    assert not (tmp_path / "out").exists() and debris(tmp_path) == []


# where a kill -9 lands: during the encoder's frame (only the encoder's process dies), with the
# temporary store complete, after an episode is written, with the dataset complete but not
# published, and after it is published
KILLS = ["convert.encode", "convert.ingested", "convert.episode", "convert.written",
         "convert.published", "convert.cleanup.half"]


@pytest.mark.parametrize("point", KILLS)
def test_a_rerun_after_kill_9_leaves_no_debris(v21, tmp_path, point):
    out = tmp_path / "out"
    p = child(tmp_path, "convert", v21, "--out", out, fault=point)
    _, err = p.communicate(timeout=120)
    if point == "convert.encode":  # the encoder's process was killed: said, and cleaned up
        assert p.returncode == 1 and "encoder process died (exit code -9) on episode 0" in err
        assert debris(tmp_path) == []
    else:
        assert p.returncode == -signal.SIGKILL, err
        assert debris(tmp_path)  # what the killed run left: removed by the next
    r = sefa(tmp_path, "convert", v21, "--out", out)
    if point in ("convert.published", "convert.cleanup.half"):  # published before the kill
        one_error(r, "out: already exists")
    else:
        assert r.returncode == 0, r.stderr
    assert json.loads((out / "meta/info.json").read_text())["total_frames"] == 11
    assert debris(tmp_path) == []


def test_a_live_conversions_temporaries_are_not_touched(v21, tmp_path):
    """Only a dead process's leftovers are removed: this (live) process's pid is not cleaned."""
    from sefa_data.atomic import remove_dead_temporaries

    live = tmp_path / f".out.store-{os.getppid()}"
    live.mkdir()
    dead = tmp_path / ".out.tmp-999999999"
    dead.mkdir()
    assert remove_dead_temporaries(tmp_path / "out", ("tmp", "store")) == [dead]
    assert live.is_dir() and not dead.exists()


def test_an_interrupt_after_publishing_says_the_dataset_is_complete(v21, tmp_path, monkeypatch):
    monkeypatch.setenv("SEFA_FAULT", "convert.published:sigint")
    r = sefa(tmp_path, "convert", v21, "--out", tmp_path / "out")
    assert r.returncode == 130
    assert r.stderr.strip().splitlines()[-1] == \
        f"interrupted after {tmp_path / 'out'} was written: it is complete (the temporary " \
        "files are removed)"
    assert (tmp_path / "out/meta/info.json").is_file() and debris(tmp_path) == []


# the final cleanup, step by step: the dataset published, the temporary store's removal begun
# (interrupts held), the store removed but not its folder, all removed (still held)
CLEANUP = ["convert.published", "convert.cleanup", "convert.cleanup.half", "convert.cleanup.done"]


@pytest.mark.parametrize("point", CLEANUP)
def test_sigterm_at_each_step_of_the_final_cleanup_leaves_no_temporary(v21, tmp_path, point):
    """A SIGTERM (a scheduler's, `kill`) while the temporary store is removed once left
    `.out.store-PID` beside a complete dataset: the removal is not cut, the dataset stays, the
    last line says both, and the next run finds nothing to remove."""
    out = tmp_path / "out"
    p = child(tmp_path, "convert", v21, "--out", out, fault=f"{point}:sigterm")
    _, err = p.communicate(timeout=120)
    assert p.returncode == 130, err
    assert err.strip().splitlines()[-1] == \
        f"interrupted after {out} was written: it is complete (the temporary files are removed)"
    assert debris(tmp_path) == [] and "Traceback" not in err
    assert json.loads((out / "meta/info.json").read_text())["total_frames"] == 11
    r = sefa(tmp_path, "convert", v21, "--out", out)
    one_error(r, "out: already exists")
    assert debris(tmp_path) == []


def test_a_temporary_the_file_system_keeps_is_named_with_who_removes_it(v21, tmp_path,
                                                                         monkeypatch):
    """A removal that fails (here: refused for the store's folder) is said on the run's last
    line, with the command that removes it (that it does, once this process is dead, is
    test_a_rerun_after_kill_9_leaves_no_debris's case)."""
    import shutil

    from sefa_data import atomic

    real = shutil.rmtree
    monkeypatch.setattr(atomic.shutil, "rmtree", lambda path, ignore_errors=False: None
                        if Path(path).name.startswith(".out.store-") else real(path, ignore_errors))
    r = sefa(tmp_path, "convert", v21, "--out", tmp_path / "out")
    assert r.returncode == 0, r.stderr
    left = tmp_path / f".out.store-{os.getpid()}"
    assert r.stderr.strip().splitlines()[-1] == (
        f"note: {left} is left beside it: the next `sefa convert` to {tmp_path / 'out'} "
        "removes it (or remove it yourself)")
    assert debris(tmp_path) == [left.name]


def test_inputs_tasks_and_targets_are_checked_before_any_input_is_read(v21, tmp_path):
    # a missing second input: refused before the first is ingested
    r = sefa(tmp_path, "convert", v21, tmp_path / "nope", "--out", tmp_path / "out")
    one_error(r, "nope: no such file or directory")
    assert "read: " not in r.stdout + r.stderr
    (tmp_path / "notes.txt").write_text("not a recording")
    r = sefa(tmp_path, "convert", v21, tmp_path / "notes.txt", "--out", tmp_path / "out")
    one_error(r, "notes.txt: unknown input format")
    assert "read: " not in r.stdout + r.stderr
    (tmp_path / "notes.txt").unlink()
    r = sefa(tmp_path, "convert", v21, "--task", "", "--out", tmp_path / "out")
    one_error(r, "--task: an empty task string")
    r = sefa(tmp_path, "convert", v21, "--task", "  ", "--out", tmp_path / "out")
    one_error(r, "--task: an empty task string")
    (tmp_path / "dangling").symlink_to(tmp_path / "nowhere")
    r = sefa(tmp_path, "convert", v21, "--out", tmp_path / "dangling")
    one_error(r, f"{tmp_path / 'dangling'}: is a dangling symlink")
    assert os.path.islink(tmp_path / "dangling") and not (tmp_path / "nowhere").exists()
    (tmp_path / "afile").write_text("x")
    r = sefa(tmp_path, "convert", v21, "--out", tmp_path / "afile" / "out")
    one_error(r, f"{tmp_path / 'afile' / 'out'}: {tmp_path / 'afile'} is not a folder")
    assert (tmp_path / "afile").read_text() == "x"
    assert debris(tmp_path) == [] and not (tmp_path / "out").exists()


def test_the_notes_speak_of_the_conversion_not_of_its_temporary_store(tmp_path):
    """A dataset without `action`: ingest's advice about `sefa train` and the temporary store's
    name are not a conversion's business; what was read from each input is."""
    write_v21(tmp_path / "v21", lengths=(6, 5))
    r = sefa(tmp_path, "convert", tmp_path / "v21", "--key", "observation.state",
             "--out", tmp_path / "out")
    assert r.returncode == 0, r.stderr
    text = r.stdout + r.stderr
    assert f"read: {tmp_path / 'v21'}: 2 episodes, 11 frames" in text
    assert ".store-" not in text and "sefa train" not in text and "written: " + str(
        tmp_path / "v21") not in text


def test_ingest_says_where_it_wrote(v21, tmp_path):
    """`sefa ingest` names the store it appended to (the workspace's default or --out)."""
    r = sefa(tmp_path, "ingest", v21, "-w", tmp_path / "ws")
    assert r.returncode == 0, r.stderr
    assert r.stderr.splitlines()[-1] == f"store: {tmp_path / 'ws' / 'dataset.zarr'}: 2 episodes, " \
                                        "11 frames appended"
    r = sefa(tmp_path, "ingest", v21, "--out", tmp_path / "other.zarr")
    assert r.stderr.splitlines()[-1] == f"store: {tmp_path / 'other.zarr'}: 2 episodes, 11 " \
                                        "frames appended"
