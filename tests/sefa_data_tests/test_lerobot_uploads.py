"""LeRobot datasets as others publish them: shapes their writers declare, uploads that lack
their files, the messages sefa gives for them (issues 46 and 49).

The datasets are written here with pyarrow and PyAV by the layout LeRobot 0.6.1's own writer
produces (tests/lerobot_v30.py says how that was checked), or by tests/sefa_data_tests/
test_lerobot.py's v2.1 writer; no real published file covers these cases.
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq

from cli_inprocess import run_cli
from lerobot_v30 import DATA, EPISODES, lfs_pointer, video_file, write_v30
from sefa_data.lerobot.reader import read_lerobot
from sefa_data.store.zarr_store import EpisodeStore
from test_lerobot import write_v21
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


def test_a_policy_trains_on_an_action_declared_one_by_two_and_predicts_vectors(tmp_path):
    """The stored (N, 1, 2) action is the policy's 2-vector per frame (the sampler drops the
    unit axis, as LeRobot's frames are read): training runs (it stopped on mismatched shapes),
    the expert chunks are the frames' values, and a chunk comes back as (T, 2)."""
    from sefa_data.sampler import SequenceSampler
    from sefa_model.policy import Policy

    root = tmp_path / "ds"
    truth = write_v30(root, lengths=(20, 18), action_shape=(1, 2), cameras=())
    assert sefa("ingest", root, "-w", tmp_path / "ws").returncode == 0
    store = EpisodeStore.open(tmp_path / "ws" / "dataset.zarr")
    windows = SequenceSampler(store, horizon=16, n_obs_steps=2, n_action_steps=8)
    first = windows.actions(np.array([0]))[0]
    assert first.shape == (16, 2)
    frames = windows.frame_indices(np.array([0]))[0]  # edge padding included
    np.testing.assert_array_equal(first, truth["action"][frames, 0])
    np.testing.assert_array_equal(windows.window(0)["action"], first)
    r = sefa("train", "policy.head=mlp", "policy.mlp_hidden_dims=[16,16]", "training.max_steps=2",
             "training.batch_size=8", "training.val_every=2", "training.checkpoint_every=2",
             "training.val_sample_windows=2", "training.val_batches=1",
             "-w", tmp_path / "ws")
    assert r.returncode == 0, r.stderr[-2000:]
    policy = Policy.load(tmp_path / "ws" / "train", device="cpu")
    obs = {"observation.state": truth["state"][None, :2]}
    assert policy.predict_action(obs, solver="euler", steps=1).action_pred.shape == (1, 16, 2)


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


# ------------------------------------------------------------------ uploads without their files


def test_an_upload_of_the_tables_alone_is_not_said_to_be_readable(tmp_path):
    """meta/ without data/ and videos/ (five of fifteen uploads seen): inspect says no feature
    is read and exits 1 with the line ingest gives, which names every file in one run."""
    root = tmp_path / "ds"
    write_v30(root, cameras=("observation.images.a", "observation.images.b"))
    for folder in ("data", "videos"):
        shutil.rmtree(root / folder)
    r = sefa("inspect", root, "--json")
    assert r.returncode == 1, r.stdout + r.stderr
    summary = json.loads(r.stdout)
    assert not any(f["read"] for f in summary["features"].values()), summary["features"]
    assert summary["skipped"]["observation.images.a"] == "video files missing"
    assert summary["skipped"]["action"] == "data files missing"
    line = one_error(sefa("inspect", root))
    assert line == (
        f"error: {root}: 3 files the episodes table points to are missing (1 data parquet file "
        "and 2 video files): data/chunk-000/file-000.parquet, videos/observation.images.a/"
        "chunk-000/file-000.mp4, videos/observation.images.b/chunk-000/file-000.mp4 (no data/ "
        "and no videos/ folder: an upload of the tables alone; fetch the dataset's files too)")
    assert one_error(sefa("ingest", root, "--out", tmp_path / "s.zarr")) == line
    assert not (tmp_path / "s.zarr").exists()


def test_every_missing_video_is_named_in_one_run(tmp_path):
    """Seven videos of eight episodes missing: one line counts them and names the first few."""
    root = tmp_path / "v21"
    write_v21(root, lengths=(3,) * 8)
    for e in range(1, 8):
        (root / f"videos/chunk-000/observation.images.cam/episode_{e:06d}.mp4").unlink()
    line = one_error(sefa("ingest", root, "--out", tmp_path / "s.zarr"))
    assert line == (
        f"error: {root}: 7 files the episodes table points to are missing (7 video files): "
        + ", ".join(f"videos/chunk-000/observation.images.cam/episode_{e:06d}.mp4"
                    for e in (1, 2, 3)) + " and 4 more")
    assert one_error(sefa("inspect", root)) == line
    # without the camera, nothing is missing
    assert sefa("ingest", root, "--out", tmp_path / "s.zarr", "--key", "action").returncode == 0


def test_git_lfs_pointers_are_said_to_be_pointers_with_the_command_that_fetches_them(tmp_path):
    """A clone made without Git LFS: parquet and mp4 files are 130-byte pointers. Said as such
    (not "truncated or damaged"), with `git lfs pull`; an episodes table that is a pointer
    too."""
    root = tmp_path / "ds"
    write_v30(root)
    lfs_pointer(root / DATA)
    lfs_pointer(video_file(root, "observation.images.cam"))
    line = one_error(sefa("ingest", root, "--out", tmp_path / "s.zarr"))
    assert line == (
        f"error: {root}: 2 files are Git LFS pointers, not the files themselves (data/chunk-000/"
        "file-000.parquet, videos/observation.images.cam/chunk-000/file-000.mp4): the clone has "
        "not fetched them; run `git lfs pull` inside the clone to fetch the files themselves")
    assert one_error(sefa("inspect", root)) == line
    lfs_pointer(root / EPISODES)
    line = one_error(sefa("inspect", root))
    size = (root / EPISODES).stat().st_size
    assert line == (f"error: {root / EPISODES}: a Git LFS pointer ({size} bytes), not the file "
                    "itself: the clone has not fetched it; run `git lfs pull` inside the clone "
                    "to fetch the files themselves")


def test_a_library_message_is_never_cut_mid_word(tmp_path):
    """pyarrow's message for a damaged table names its path and runs past the length sefa
    quotes ("... Either the file is corrupted or th"): it is cut after a whole word, and says
    it was cut."""
    root = tmp_path / "ds"
    write_v30(root)
    table = root / EPISODES
    table.write_bytes(table.read_bytes()[:200])
    line = one_error(sefa("ingest", root, "--out", tmp_path / "s.zarr"))
    quoted = line[line.index("unreadable parquet (") + 20:line.rindex("): truncated")]
    theirs = pyarrow_message(table)
    assert len(theirs) > 160 and quoted.endswith(" ..."), (quoted, theirs)
    # the quoted part ends on one of pyarrow's whole words (pyarrow itself shortens a long path
    # in some of its messages, so the words are compared, with the path as it is)
    kept = quoted.removesuffix(" ...").split()
    assert kept[-1] in {*theirs.split(), f"'{table}'", f"'{table}':"}, (quoted, theirs)
    assert all(word in theirs or str(table) in word for word in kept), (quoted, theirs)
    from sefa_data.errors import clip

    text = "Either the file is corrupted or this is not a parquet file"
    assert clip(text, 34) == "Either the file is corrupted or ..."
    assert clip(text, 200) == text


def pyarrow_message(path: Path) -> str:
    """pyarrow's own message for the file, on one line."""
    try:
        pq.read_table(path)
    except Exception as e:  # noqa: BLE001 (whatever pyarrow raises: its words)
        return " ".join(str(e).split())
    return ""


def test_key_leaves_out_a_camera_the_episodes_table_does_not_place(tmp_path):
    """An episodes table without videos/CAM/from_timestamp: the camera cannot be read (said as
    a missing column, with --key), and --key leaves it out; the rest reads exactly."""
    root = tmp_path / "ds"
    truth = write_v30(root, cameras=("observation.images.a", "observation.images.b"))
    table = pq.read_table(root / EPISODES)
    pq.write_table(table.drop(["videos/observation.images.b/from_timestamp"]), root / EPISODES)
    line = one_error(sefa("ingest", root, "--out", tmp_path / "s.zarr"))
    assert line == (
        f"error: {root / EPISODES}: observation.images.b: the episodes table has no column "
        "videos/observation.images.b/from_timestamp: where each episode's frames are in this "
        "camera's video is not known, so it cannot be read; leave it out with --key (--key "
        "observation.state --key action --key observation.images.a)")
    assert "must be a time" not in line
    r = sefa("ingest", root, "--out", tmp_path / "s.zarr", "--key", "observation.state",
             "--key", "action", "--key", "observation.images.a")
    assert r.returncode == 0, r.stderr
    store = EpisodeStore.open(tmp_path / "s.zarr")
    assert np.array_equal(store.root["data"]["action"][:], truth["action"])
    assert sorted(store.attrs["features"]) == ["action", "observation.images.a",
                                               "observation.state"]
    summary = json.loads(sefa("inspect", root, "--json").stdout)
    assert [k for k, f in summary["features"].items() if not f["read"]] == ["observation.images.b"]


# ------------------------------------------------------------------ what convert says


def test_convert_says_nothing_that_belongs_to_training(tmp_path):
    """One episode whose action never changes: ingest notes the window-level split and the
    constant action (naming the input); a conversion trains nothing and says neither."""
    root = tmp_path / "one"
    write_v30(root, lengths=(6,), cameras=(), action=np.zeros((6, 2)))
    r = sefa("convert", root, "--out", tmp_path / "lr")
    assert r.returncode == 0, r.stderr
    text = r.stdout + r.stderr
    assert "validation" not in text and "constant" not in text and "map" not in text, text
    assert "note:" not in text and "warning:" not in text, text
    r = sefa("ingest", root, "--out", tmp_path / "s.zarr")
    assert r.returncode == 0, r.stderr
    assert "validation split" in r.stderr and "`action` is constant (0, 0 in all 6 frames)" \
        in r.stderr and f"; {root}: check that its `action` feature" in r.stderr, r.stderr
