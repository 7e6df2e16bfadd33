"""An input that is not a recording file or folder, through the real `sefa ingest` and `sefa
inspect`: one true line (not "no such file"), exit 1, no store written, and a FIFO is never
opened (opening it for reading would block until a writer came)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


def sefa(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "sefa_cli.main", *map(str, args)], capture_output=True,
                          text=True, cwd=REPO, timeout=120,
                          env={**os.environ, "PYTHONPATH": str(REPO)})


def fifo(tmp: Path) -> Path:
    os.mkfifo(tmp / "pipe.hdf5")
    return tmp / "pipe.hdf5"


def loop(tmp: Path) -> Path:
    (tmp / "a.bag").symlink_to(tmp / "b.bag")
    (tmp / "b.bag").symlink_to(tmp / "a.bag")
    return tmp / "a.bag"


def dangling(tmp: Path) -> Path:
    (tmp / "gone.mcap").symlink_to(tmp / "elsewhere.mcap")
    return tmp / "gone.mcap"


def folder(tmp: Path) -> Path:
    (tmp / "demos.hdf5").mkdir()
    return tmp / "demos.hdf5"


CASES = {
    "fifo": (fifo, "not a regular file but a FIFO (named pipe)"),
    "/dev/null": (lambda tmp: Path("/dev/null"), "not a regular file but a character device"),
    "symlink loop": (loop, "a symlink loop"),
    "dangling symlink": (dangling, "a dangling symlink"),
    "directory": (folder, "a directory, where a file is expected (a .hdf5 recording is one file)"),
}


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX file kinds")
@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("command", ["ingest", "inspect"])
def test_an_input_that_is_not_a_recording_is_said_for_what_it_is(tmp_path, case, command):
    make, what = CASES[case]
    path = make(tmp_path)
    args = [command, path] + (["--out", tmp_path / "s.zarr"] if command == "ingest" else [])
    r = sefa(*args)  # a FIFO opened for reading would hang here until the timeout
    assert r.returncode == 1, r.stderr
    assert r.stderr.strip().splitlines()[-1].startswith(f"error: {path}: {what}")
    assert "no such file" not in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "s.zarr").exists()


def raw_robosuite(path: Path, lengths: dict[str, tuple[int, int]]) -> Path:
    """A raw robosuite recording (no obs/): per demo (actions, states) rows, and a side stream
    of its own rate (which is left out, as the handover file's user logs are)."""
    import h5py
    import numpy as np

    with h5py.File(path, "w") as f:
        for demo, (n_actions, n_states) in lengths.items():
            f[f"data/{demo}/actions"] = np.zeros((n_actions, 7))
            f[f"data/{demo}/states"] = np.zeros((n_states, 32))
            f[f"data/{demo}/user_info/clutch"] = np.zeros(2 * n_actions)
    return path


def test_robosuite_states_of_another_length_is_an_error_naming_demo_and_lengths(tmp_path):
    """README's promise for a raw robosuite file: the observation (`states`) of another length
    than the actions stops the ingest naming the demo and both lengths; --skip-bad-demos skips
    that demo with a warning. It used to drop `state` from every demo with a warning (exit 0:
    a store with no observation at all)."""
    src = raw_robosuite(tmp_path / "raw.hdf5",
                        {"demo_1": (5, 5), "demo_2": (4, 6), "demo_3": (3, 3)})
    out = tmp_path / "s.zarr"
    r = sefa("ingest", src, "--fps", "20", "--out", out)
    assert r.returncode == 1, r.stderr
    assert r.stderr.strip().splitlines()[-1] == (
        f"error: {src}: data/demo_2/states: 6 rows for 4 actions (every demo needs it; "
        "--skip-bad-demos skips such demos with a warning)")
    assert not out.exists()
    r = sefa("ingest", src, "--fps", "20", "--out", out, "--skip-bad-demos")
    assert r.returncode == 0, r.stderr
    assert (f"warning: {src}: skipped demo demo_2 (--skip-bad-demos): data/demo_2/states: 6 rows "
            "for 4 actions") in r.stderr
    from sefa_data.store.zarr_store import EpisodeStore

    store = EpisodeStore.open(out)
    assert list(store.episode_ends) == [5, 8] and "state" in store.root["data"]
