"""Other people's LeRobot datasets, and damaged ones, through the reader (issues 32 and 33).

Each bad dataset is made from a real one (tests/lerobot_faults.py): the Push-T image fixture
in ../shared/data (written by LeRobot 0.6.1) copied and edited with pyarrow and json, or the
small v2.1 dataset that tests/sefa_data_tests/test_lerobot.py writes with pyarrow and PyAV. The tasks tables
indexed by task were written by pandas itself (tests/data/lerobot_tasks/make_tasks.py: the
project does not depend on pandas). Every refusal is one line naming the file and the key,
exit 1, no store written; the same cases run in the bad-input catalogue.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from cli_inprocess import run_cli
from lerobot_faults import (DATA, EPISODES, IMAGES, MALFORMED, TASKS, edit_episodes, edit_info,
                            flip_bit_on_disk, image_copy, nan_timestamp, split_in_two_data_files)
from sefa_data.errors import SefaInputError
from sefa_data.lerobot.reader import read_lerobot
from sefa_data.store.zarr_store import EpisodeStore
from test_lerobot import write_v21

REPO = Path(__file__).resolve().parents[2]


def sefa(*args) -> subprocess.CompletedProcess:
    return run_cli(*args, cwd=REPO)


def refused(root: Path, out: Path, *extra) -> str:
    """`sefa ingest ROOT --out OUT`: exit 1, one error line, no traceback, no store."""
    r = sefa("ingest", root, "--out", out, *extra)
    errors = [ln for ln in r.stderr.splitlines() if ln.startswith("error: ")]
    assert r.returncode == 1 and len(errors) == 1, r.stdout + r.stderr
    assert "Traceback" not in r.stderr and "a bug in sefa" not in r.stderr, r.stderr
    assert not out.exists()
    return errors[0]








# ------------------------------------------------------------------ how LeRobot writes them


@pytest.mark.parametrize("written", ["tasks_unnamed_index", "tasks_named_index"])
def test_tasks_table_written_by_pandas_with_the_task_as_index(shared_data, tmp_path, written):
    """meta/tasks.parquet as pandas writes a DataFrame indexed by task (unnamed index: pyarrow
    shows `__index_level_0__`): read, ingested and converted, as LeRobot reads it."""
    root = image_copy(shared_data, tmp_path)
    shutil.copy(TASKS / f"{written}.parquet", root / "meta/tasks.parquet")
    rec = read_lerobot(root, keys=["action"])
    assert rec.meta["tasks"] == ["Push the T-shaped block onto the target.", "Pick up the red cube."]
    r = sefa("ingest", root, "--out", tmp_path / "s.zarr")
    assert r.returncode == 0, r.stderr
    r = sefa("convert", root, "--out", tmp_path / "lr", "--codec", "h264")
    assert r.returncode == 0, r.stderr
    back = read_lerobot(tmp_path / "lr", keys=["action"])
    assert back.meta["tasks"] == ["Push the T-shaped block onto the target."]
    assert back.meta["episode_tasks"] == [["Push the T-shaped block onto the target."]] * 5
    lerobot_check(tmp_path / "lr")


def lerobot_check(root: Path) -> None:
    """LeRobot 0.6.1 itself loads `root` (../shared/tools/lerobot_check.sh), where its venv was
    built (the script would otherwise spend minutes and 5 GB building it inside a test)."""
    venv = Path(os.environ.get("LEROBOT_CHECK_VENV", Path.home() / ".cache/sefa-lerobot-check"))
    script = REPO.parent / "shared/tools/lerobot_check.sh"
    if not script.is_file() or not (venv / "bin/python").is_file() or subprocess.run(
            [str(venv / "bin/python"), "-c", "import lerobot"], capture_output=True).returncode:
        pytest.skip(f"LeRobot's checker is not built here ({venv}: run {script} once)")
    r = subprocess.run(["bash", str(script), str(root)], capture_output=True, text=True,
                       timeout=600)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]


def test_v21_path_templates_with_any_of_lerobots_field_names(tmp_path):
    """A community writer's `{chunk_index}` (and `{file_index}`) in a v2.1 template reads
    the same files as LeRobot's own `{episode_chunk}`."""
    root = tmp_path / "v21"
    truth = write_v21(root)
    edit_info(root, lambda i: i.update(
        data_path="data/chunk-{chunk_index:03d}/episode_{file_index:06d}.parquet",
        video_path="videos/chunk-{chunk_index:03d}/{video_key}/episode_{episode_index:06d}.mp4"))
    eps = list(read_lerobot(root).episodes)
    for e, ep in enumerate(eps):
        assert np.array_equal(ep.data["observation.state"], truth["state"][e])
    assert [len(e) for e in eps] == [12, 9]


def test_v20_dataset_reads_as_v21(tmp_path):
    """v2.0 differs from v2.1 only by the per-episode statistics that LeRobot's own v2.0 ->
    v2.1 conversion computes; sefa reads it as v2.1."""
    root = tmp_path / "v20"
    truth = write_v21(root)
    edit_info(root, lambda i: i.update(codebase_version="v2.0"))
    rec = read_lerobot(root)
    eps = list(rec.episodes)
    assert rec.meta["codebase_version"] == "v2.0"
    assert np.array_equal(eps[1].data["action"], truth["action"][1])


def test_robot_type_and_nested_names_kept_through_ingest_and_convert(tmp_path):
    """names [[...]] as Unitree writes them, and robot_type: in the store and in what
    `sefa convert` writes."""
    root = tmp_path / "v21"
    write_v21(root)

    def unitree(info):
        info["robot_type"] = "unitree_g1"
        info["features"]["observation.state"]["names"] = [["kLeftHip", "kRightHip", "kWaist"]]
        info["features"]["action"]["names"] = {"motors": ["left", "right"]}
    edit_info(root, unitree)
    r = sefa("ingest", root, "--out", tmp_path / "s.zarr")
    assert r.returncode == 0, r.stderr
    features = EpisodeStore.open(tmp_path / "s.zarr").attrs["features"]
    assert features["observation.state"]["names"] == ["kLeftHip", "kRightHip", "kWaist"]
    assert features["action"]["names"] == ["left", "right"]
    for src in (root, tmp_path / "s.zarr"):  # a LeRobot folder, and the store it became
        out = tmp_path / f"lr-{src.name}"
        r = sefa("convert", src, "--out", out, "--codec", "h264")
        assert r.returncode == 0, r.stderr
        info = json.loads((out / "meta/info.json").read_text())
        assert info["robot_type"] == "unitree_g1"
        assert info["features"]["observation.state"]["names"] == ["kLeftHip", "kRightHip", "kWaist"]
    # --robot-type still wins
    r = sefa("convert", root, "--out", tmp_path / "lr-given", "--codec", "h264",
             "--robot-type", "so101")
    assert json.loads((tmp_path / "lr-given/meta/info.json").read_text())["robot_type"] == "so101"


def test_robot_type_of_the_real_fixture_kept(shared_data, tmp_path):
    r = sefa("convert", shared_data / IMAGES, "--out", tmp_path / "lr", "--codec", "h264")
    assert r.returncode == 0, r.stderr
    assert json.loads((tmp_path / "lr/meta/info.json").read_text())["robot_type"] == "pusht"


# ------------------------------------------------------------------ files checked first


@pytest.fixture
def opened(monkeypatch) -> list:
    """The video files PyAV opens from here on (none may be, before a refusal)."""
    import av

    calls = []
    real_open = av.open
    monkeypatch.setattr(av, "open", lambda *a, **k: calls.append(a) or real_open(*a, **k))
    return calls


def test_missing_video_refused_before_any_decoding(tmp_path, opened):
    root = tmp_path / "v21"
    write_v21(root, lengths=(6, 5, 7))
    opened.clear()  # the videos just written
    missing = root / "videos/chunk-000/observation.images.cam/episode_000002.mp4"
    missing.unlink()
    with pytest.raises(SefaInputError) as e:
        read_lerobot(root)  # before the first episode is asked for
    assert e.value.file == str(missing) and e.value.key == "observation.images.cam"
    assert "missing video file" in e.value.line() and opened == []
    line = refused(root, tmp_path / "s.zarr")
    assert "episode_000002.mp4: observation.images.cam: missing video file" in line
    assert opened == []


def test_missing_data_file_refused_before_any_decoding(tmp_path, opened):
    root = tmp_path / "v21"
    write_v21(root, lengths=(6, 5, 7))
    opened.clear()  # the videos just written
    (root / "data/chunk-000/episode_000002.parquet").unlink()
    line = refused(root, tmp_path / "s.zarr")
    assert "episode_000002.parquet: missing (the episodes table points to it)" in line
    assert opened == []




def test_two_data_files_read_as_one_and_a_wrong_file_index_is_named(shared_data, tmp_path):
    whole = [ep.data["action"] for ep in read_lerobot(shared_data / IMAGES, keys=["action"]).episodes]
    root = image_copy(shared_data, tmp_path)
    split_in_two_data_files(root)
    split = [ep.data["action"] for ep in read_lerobot(root, keys=["action"]).episodes]
    assert all(np.array_equal(a, b) for a, b in zip(whole, split))
    edit_episodes(root, "data/file_index", 3, 0)  # episode 3's rows are in file-001
    line = refused(root, tmp_path / "s.zarr")
    assert f"{root / EPISODES}: data/file_index: episode 3 points to " \
           "data/chunk-000/file-000.parquet (row 420), but its rows are in " \
           "data/chunk-000/file-001.parquet" in line


# ------------------------------------------------------------------ values as info.json says


@pytest.mark.parametrize("dtype, example", [("int8", "becomes"), ("uint8", "becomes")])
def test_lossy_dtype_refused_unless_asked(shared_data, tmp_path, dtype, example):
    """A float action declared int8 / uint8: refused with an example value; with
    --allow-lossy-cast it is cast as asked."""
    root = image_copy(shared_data, tmp_path)
    edit_info(root, lambda i: i["features"]["action"].update(dtype=dtype))
    line = refused(root, tmp_path / "s.zarr")
    assert f"{root / DATA}: action: info.json's dtype {dtype} cannot hold these values: " \
           "float32 value" in line and example in line and "--allow-lossy-cast" in line
    r = sefa("ingest", root, "--out", tmp_path / "s.zarr", "--allow-lossy-cast")
    assert r.returncode == 0, r.stderr
    store = EpisodeStore.open(tmp_path / "s.zarr")
    raw = pq.read_table(root / DATA).column("action").combine_chunks().flatten().to_numpy()
    with np.errstate(all="ignore"):
        assert np.array_equal(store.root["data"]["action"][:].ravel(), raw.astype(dtype))


def test_lossless_dtype_reads(shared_data, tmp_path):
    """float32 values declared float64 change nothing: read."""
    root = image_copy(shared_data, tmp_path)
    edit_info(root, lambda i: i["features"]["action"].update(dtype="float64"))
    ep = next(read_lerobot(root, keys=["action"]).episodes)
    raw = pq.read_table(root / DATA).column("action").combine_chunks().flatten().to_numpy()
    assert ep.data["action"].dtype == np.float64
    assert np.array_equal(ep.data["action"].ravel(), raw[:ep.data["action"].size])




def test_flipped_bit_caught_by_the_episode_statistics(shared_data, tmp_path):
    root = image_copy(shared_data, tmp_path)
    before, after = flip_bit_on_disk(root / DATA, "action", 170, bit=29)
    assert abs(after) > 1e20  # the exponent bit: a 4.6e21 action, as the issue found
    line = refused(root, tmp_path / "s.zarr")
    assert f"{root / DATA}: action: value " in line and "as read but" in line
    assert "in the dataset's own statistics of this episode" in line
    assert "(at episode 1)" in line and f"{after:.9g}" in line
    # asked to, it reads the damaged value (for a dataset whose statistics are stale)
    r = sefa("ingest", root, "--out", tmp_path / "s.zarr", "--skip-stats-check")
    assert r.returncode == 0, r.stderr
    assert np.float32(after) in EpisodeStore.open(tmp_path / "s.zarr").root["data"]["action"][:]


def test_valid_fixtures_pass_the_statistics_and_their_tolerance_is_tight(shared_data, tmp_path):
    """The statistics check is on for the real fixtures (they pass: every exact-equality test
    reads them) and catches a change far smaller than a flipped exponent bit: one action
    raised by one pixel above its episode's maximum (the mean's looser tolerance is for
    float32 sums; the extremes are stored exactly)."""
    from sefa_data.lerobot.layout import load_layout

    layout = load_layout(shared_data / IMAGES)
    assert set(layout.episodes[0].stats) == {"observation.state", "action"}
    root = image_copy(shared_data, tmp_path)
    table = pq.read_table(root / DATA)
    action = table.column("action").combine_chunks()
    values = action.flatten().to_numpy().copy()
    top = int(np.argmax(values[0:161 * 2:2])) * 2  # episode 0's largest x
    values[top] += 1.0
    i = table.schema.get_field_index("action")
    pq.write_table(table.set_column(i, table.schema.field(i), pa.FixedSizeListArray.from_arrays(
        pa.array(values), 2)), root / DATA)
    line = refused(root, tmp_path / "s.zarr")
    assert f"action: value 0 has max {values[top]:.9g} as read but {values[top] - 1:.9g}" in line
    assert "(at episode 0)" in line


def test_nan_timestamp_refused(tmp_path):
    """A NaN timestamp compared False with the grid's tolerance and took the previous video
    frame."""
    root = tmp_path / "v21"
    write_v21(root)
    path = root / "data/chunk-000/episode_000001.parquet"
    nan_timestamp(path, 4)
    line = refused(root, tmp_path / "s.zarr")
    assert f"{path}: timestamp: timestamp nan is not a finite number of seconds" in line
    assert "(at episode 1, frame 4)" in line


# ------------------------------------------------------------------ malformed tables










@pytest.mark.parametrize("name", list(MALFORMED))
def test_malformed_values_are_one_line_naming_file_and_key(shared_data, tmp_path, name):
    damage, file, key, words = MALFORMED[name]
    root = image_copy(shared_data, tmp_path)
    damage(root)
    line = refused(root, tmp_path / "s.zarr")
    assert line.startswith(f"error: {root / file}: {key}: ") and words in line, line


def test_video_path_null_with_a_video_feature(tmp_path):
    root = tmp_path / "v21"
    write_v21(root)
    edit_info(root, lambda i: i.update(video_path=None))
    line = refused(root, tmp_path / "s.zarr")
    assert line == f"error: {root / 'meta/info.json'}: video_path: must be a path template " \
                   "string, got None"


def test_v21_episode_statistics_checked(tmp_path):
    """v2.1 keeps its per-episode statistics in meta/episodes_stats.jsonl (as LeRobot's
    v2.0 -> v2.1 conversion writes them, json): the same check."""
    root = tmp_path / "v21"
    truth = write_v21(root)
    rows = [{"episode_index": e, "stats": {k: {"min": v.min(0).tolist(), "max": v.max(0).tolist(),
                                                "mean": v.mean(0).tolist(), "count": [len(v)]}
                                           for k, v in (("observation.state", truth["state"][e]),
                                                        ("action", truth["action"][e]))}}
            for e in range(2)]
    (root / "meta/episodes_stats.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    eps = list(read_lerobot(root).episodes)
    assert np.array_equal(eps[1].data["action"], truth["action"][1])
    rows[1]["stats"]["action"]["max"][1] += 0.5
    (root / "meta/episodes_stats.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    line = refused(root, tmp_path / "s.zarr")
    assert "episode_000001.parquet: action: value 1 has max" in line and "(at episode 1)" in line
