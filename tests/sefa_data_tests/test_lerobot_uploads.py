"""LeRobot datasets as others publish them: shapes their writers declare, uploads that lack
their files, the messages sefa gives for them (issues 46 and 49).

The datasets are written here with pyarrow and PyAV by the layout LeRobot 0.6.1's own writer
produces (tests/lerobot_v30.py says how that was checked), or by tests/sefa_data_tests/
test_lerobot.py's v2.1 writer; no real published file covers these cases.
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest

from cli_inprocess import run_cli
from lerobot_v30 import TASK, write_v30
from sefa_data.lerobot.reader import read_lerobot
from sefa_data.store.zarr_store import EpisodeStore
from test_lerobot_reader_faults import lerobot_check

REPO = Path(__file__).resolve().parents[2]


def sefa(*args, cwd: Path = REPO) -> subprocess.CompletedProcess:
    return run_cli(*args, cwd=cwd)


def one_error(r: subprocess.CompletedProcess) -> str:
    """Exit 1, one `error:` line, no traceback and no bug; the line."""
    errors = [ln for ln in r.stderr.splitlines() if ln.startswith("error: ")]
    assert r.returncode == 1 and len(errors) == 1, r.stdout + r.stderr
    assert "Traceback" not in r.stderr and "a bug in sefa" not in r.stderr, r.stderr
    return errors[0]


# ------------------------------------------------------------------ an action declared [1, 2]


def test_an_action_declared_one_by_two_is_stored_as_lerobot_reads_it(tmp_path):
    """`"shape": [1, 2]` (a writer that keeps a leading axis of 1; LeRobot 0.6.1 declares it
    `datasets.Array2D` and returns each frame's action as a (1, 2) array): the store holds
    exactly the frames' values in that shape, and its conversion loads in LeRobot."""
    root = tmp_path / "ds"
    truth = write_v30(root, action_shape=(1, 2))
    r = sefa("ingest", root, "--out", tmp_path / "s.zarr")
    assert r.returncode == 0, r.stderr
    assert "a bug in sefa" not in r.stderr and "warning" not in r.stderr, r.stderr
    store = EpisodeStore.open(tmp_path / "s.zarr")
    action = store.root["data"]["action"][:]
    assert action.shape == (9, 1, 2) and np.array_equal(action, truth["action"])
    assert np.array_equal(store.root["data"]["observation.state"][:], truth["state"])
    assert store.episode_ends.tolist() == truth["ends"]
    r = sefa("convert", root, "--out", tmp_path / "lr", "--codec", "h264")
    assert r.returncode == 0, r.stderr
    # written flattened, as every low-dim key of more than one dimension (docs/guides/lerobot.md)
    info = json.loads((tmp_path / "lr/meta/info.json").read_text())
    assert info["features"]["action"]["shape"] == [2]
    back = np.concatenate([e.data["action"] for e in
                           read_lerobot(tmp_path / "lr", keys=["action"]).episodes])
    assert np.array_equal(back, truth["action"].reshape(9, 2))
    lerobot_check(tmp_path / "lr")


def test_a_constant_action_of_shape_one_by_two_is_said_in_one_line(tmp_path):
    """The constant-action warning formats an action of any shape (it raised on [1, 2]) and
    speaks of the input the user gave, not of a topic map it does not have."""
    root = tmp_path / "ds"
    write_v30(root, action_shape=(1, 2), action=np.tile([[[0.5, -1.0]]], (9, 1, 1)))
    r = sefa("ingest", root, "--out", tmp_path / "s.zarr")
    assert r.returncode == 0 and "a bug in sefa" not in r.stderr, r.stderr
    warning = next(ln for ln in r.stderr.splitlines() if ln.startswith("warning: "))
    assert warning == (
        f"warning: {tmp_path / 's.zarr'}: `action` is constant (0.5, -1 in all 9 frames): a "
        f"policy trained on it cannot learn anything; {root}: check that its `action` feature "
        "is the commanded one (--rename FEATURE=action reads another feature as the action)")
    assert "map" not in warning
