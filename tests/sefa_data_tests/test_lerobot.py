"""LeRobot datasets in and out (issue 21).

The v3.0 folders in ../shared/data were written by LeRobot 0.6.1's own writer, and the npz
holds what LeRobot 0.6.1 itself decoded from one of them. No v2.1 dataset was found as real
data, so `write_v21` below writes a small one in the test with pyarrow and PyAV by the
published v2.1 layout (meta/info.json, meta/episodes.jsonl, meta/tasks.jsonl, one parquet and
one H.264 video per episode); the bad-input cases are variations of it.
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from cli_inprocess import run_cli
from sefa_data.errors import SefaInputError
from sefa_data.ingest import IngestOptions, ingest
from sefa_data.lerobot.reader import inspect_lerobot, read_lerobot
from sefa_data.store.zarr_store import EpisodeStore

VIDEO = "lerobot_pusht_v30"
IMAGES = "lerobot_pusht5_image_v30"
REF = "lerobot_pusht_v30_frames_ep0_ep100.npz"
TASK = "Push the T-shaped block onto the T-shaped target."


def sefa(*args) -> subprocess.CompletedProcess:
    """`sefa ARGS` in-process through sefa_cli.main.main (tests/cli_inprocess.py)."""
    return run_cli(*args, cwd=Path(__file__).resolve().parents[2])


def parquet_column(table: pa.Table, key: str) -> np.ndarray:
    col = table.column(key).combine_chunks()
    return col.flatten().to_numpy().reshape(len(col), -1)


def png_frames(table: pa.Table, key: str) -> np.ndarray:
    import io

    from PIL import Image

    return np.stack([np.asarray(Image.open(io.BytesIO(c["bytes"])).convert("RGB"))
                     for c in table.column(key).to_pylist()])


# ------------------------------------------------------------------ v3.0, written by LeRobot


def test_video_frames_equal_what_lerobot_decoded(shared_data):
    """Episodes 0 and 100: frames, state and action equal LeRobot 0.6.1's own output."""
    ref = np.load(shared_data / REF)
    rec = read_lerobot(shared_data / VIDEO, episodes=[0, 100])
    eps = list(rec.episodes)
    assert [len(e) for e in eps] == [161, 117] and eps[1].label == "episode_index 100"
    for key in ("observation.image", "observation.state", "action"):
        got = np.concatenate([e.data[key] for e in eps])
        assert got.dtype == ref[key].dtype and got.shape == ref[key].shape
        diff = np.abs(got.astype(np.int64) - ref[key].astype(np.int64)) if key == \
            "observation.image" else np.abs(got - ref[key])
        print(f"{key}: mean |difference| against LeRobot's decoding {diff.mean():.3f}")
        assert diff.max() == 0  # the same decoder (PyAV) gives the same pixels
    assert rec.meta["tasks"] == [TASK] and rec.meta["fps"] == 10


def test_every_lowdim_array_equals_the_parquet(shared_data):
    root = shared_data / VIDEO
    data = pq.read_table(root / "data/chunk-000/file-000.parquet")
    table = pq.read_table(root / "meta/episodes/chunk-000/file-000.parquet").to_pydict()
    rec = read_lerobot(root, keys=["observation.state", "action"],  # no video decoded
                       renames={"observation.state": "observation.agent_pos"})
    eps = list(rec.episodes)
    assert len(eps) == 206 and sum(map(len, eps)) == 25650
    ends = np.cumsum([len(e) for e in eps])
    assert ends.tolist() == table["dataset_to_index"]
    for key, ours in (("observation.state", "observation.agent_pos"), ("action", "action")):
        assert np.array_equal(np.concatenate([e.data[ours] for e in eps]),
                              parquet_column(data, key))
    assert rec.meta["episode_tasks"] == table["tasks"]
    assert "observation.image" in rec.meta["skipped"]  # left out by keys=, and said so


def test_image_dataset_ingests_through_the_cli(shared_data, tmp_path):
    root = shared_data / IMAGES
    out = tmp_path / "img.zarr"
    r = sefa("ingest", root, "--out", out)
    assert r.returncode == 0, r.stderr
    store = EpisodeStore.open(out)
    data = pq.read_table(root / "data/chunk-000/file-000.parquet")
    assert store.episode_ends.tolist() == [161, 279, 420, 579, 738]
    assert store.fps == 10
    assert np.array_equal(store.root["data"]["observation.image"][:],
                          png_frames(data, "observation.image"))
    for key in ("observation.state", "action"):
        assert np.array_equal(store.root["data"][key][:], parquet_column(data, key))
    assert store.attrs["features"]["observation.state"]["names"][:2] == ["agent_x", "agent_y"]
    reader = store.attrs["sources"][0]["reader"]
    task = pq.read_table(root / "meta/tasks.parquet").to_pydict()["task"][0]
    assert reader["episode_tasks"] == [[task]] * 5 and reader["codebase_version"] == "v3.0"
    summary = inspect_lerobot(root)
    assert summary["n_episodes"] == 5 and summary["features"]["observation.image"]["dtype"] == "image"


# ------------------------------------------------------------------ v2.1, written here


def write_v21(root: Path, lengths=(12, 9), fps=10, video_short_by=0, nan_at=None,
              timestamp_jump_at=None, length_lie=None, seed=0) -> dict:
    """A LeRobot v2.1 dataset by its published layout: state, action and an H.264 video."""
    import av

    rng = np.random.default_rng(seed)
    (root / "meta").mkdir(parents=True)
    features = {
        "observation.state": {"dtype": "float32", "shape": [3], "names": ["a", "b", "c"]},
        "action": {"dtype": "float32", "shape": [2], "names": None},
        "observation.images.cam": {"dtype": "video", "shape": [64, 96, 3],
                                   "names": ["height", "width", "channel"],
                                   "info": {"video.codec": "h264", "video.fps": fps}},
        **{k: {"dtype": "int64", "shape": [1], "names": None}
           for k in ("frame_index", "episode_index", "index", "task_index")},
        "timestamp": {"dtype": "float32", "shape": [1], "names": None}}
    info = {"codebase_version": "v2.1", "robot_type": "test", "fps": fps,
            "total_episodes": len(lengths), "total_tasks": 2,
            "total_frames": sum(lengths) - lengths[0] + (length_lie or lengths[0]),
            "chunks_size": 1000, "features": features,
            "data_path": "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet",
            "video_path": "videos/chunk-{episode_chunk:03d}/{video_key}/episode_{episode_index:06d}.mp4"}
    (root / "meta/info.json").write_text(json.dumps(info))
    tasks = ["pick", "place"]
    (root / "meta/tasks.jsonl").write_text("".join(
        json.dumps({"task_index": i, "task": t}) + "\n" for i, t in enumerate(tasks)))
    (root / "meta/episodes.jsonl").write_text("".join(
        json.dumps({"episode_index": e, "tasks": [tasks[e % 2]],
                    "length": (length_lie if length_lie and e == 0 else n)}) + "\n"
        for e, n in enumerate(lengths)))
    truth, index = {"state": [], "action": [], "frames": []}, 0
    for e, n in enumerate(lengths):
        state = rng.normal(size=(n, 3)).astype(np.float32)
        if nan_at is not None and e == nan_at[0]:
            state[nan_at[1], 1] = np.nan
        action = rng.normal(size=(n, 2)).astype(np.float32)
        ts = np.arange(n, dtype=np.float32) / fps
        if timestamp_jump_at is not None and e == timestamp_jump_at[0]:
            ts[timestamp_jump_at[1]:] += 0.05
        table = pa.table({
            "observation.state": pa.FixedSizeListArray.from_arrays(pa.array(state.ravel()), 3),
            "action": pa.FixedSizeListArray.from_arrays(pa.array(action.ravel()), 2),
            "timestamp": pa.array(ts), "frame_index": pa.array(np.arange(n)),
            "episode_index": pa.array(np.full(n, e)), "index": pa.array(np.arange(index, index + n)),
            "task_index": pa.array(np.full(n, e % 2))})
        path = root / f"data/chunk-000/episode_{e:06d}.parquet"
        path.parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(table, path)
        frames = rng.integers(0, 256, size=(n, 4, 6, 3), dtype=np.uint8).repeat(16, 1).repeat(16, 2)
        video = root / f"videos/chunk-000/observation.images.cam/episode_{e:06d}.mp4"
        video.parent.mkdir(parents=True, exist_ok=True)
        with av.open(str(video), "w") as c:
            s = c.add_stream("h264", rate=fps, options={"crf": "10", "g": "2"})
            s.width, s.height, s.pix_fmt = 96, 64, "yuv420p"
            for i, img in enumerate(frames[:n - video_short_by]):
                f = av.VideoFrame.from_ndarray(img, format="rgb24")
                f.pts = i
                c.mux(s.encode(f))
            c.mux(s.encode(None))
        truth["state"].append(state)
        truth["action"].append(action)
        truth["frames"].append(frames)
        index += n
    return truth


def plain_decode(path: Path) -> np.ndarray:
    import av

    with av.open(str(path)) as c:
        return np.stack([f.to_ndarray(format="rgb24") for f in c.decode(video=0)])


def test_v21_dataset_reads_with_tasks_and_h264_frames(tmp_path):
    root = tmp_path / "v21"
    truth = write_v21(root)
    rec = read_lerobot(root)
    eps = list(rec.episodes)
    assert [len(e) for e in eps] == [12, 9]
    assert rec.meta["episode_tasks"] == [["pick"], ["place"]] and rec.meta["codebase_version"] == "v2.1"
    for e, ep in enumerate(eps):
        assert np.array_equal(ep.data["observation.state"], truth["state"][e])
        assert np.array_equal(ep.data["action"], truth["action"][e])
        got = ep.data["observation.images.cam"]
        assert np.abs(got.astype(int) - truth["frames"][e]).mean() < 3  # H.264 crf 10
        assert np.array_equal(got, plain_decode(
            root / f"videos/chunk-000/observation.images.cam/episode_{e:06d}.mp4"))


# ------------------------------------------------------------------ round trips (LeRobot out)


@pytest.fixture(scope="module")
def round_trip(shared_data, tmp_path_factory):
    """LeRobot (image fixture) -> store -> LeRobot (AV1 video) -> store."""
    tmp = tmp_path_factory.mktemp("lerobot_rt")
    ingest([shared_data / IMAGES], tmp / "a.zarr", IngestOptions())
    r = sefa("convert", tmp / "a.zarr", "--to", "lerobot", "--out", tmp / "lr")
    assert r.returncode == 0, r.stderr
    ingest([tmp / "lr"], tmp / "b.zarr", IngestOptions())
    return tmp


def test_round_trip_keeps_lowdim_identical_and_frames_within_the_codec(shared_data, round_trip):
    data = pq.read_table(shared_data / IMAGES / "data/chunk-000/file-000.parquet")
    a, b = EpisodeStore.open(round_trip / "a.zarr"), EpisodeStore.open(round_trip / "b.zarr")
    assert a.episode_ends.tolist() == b.episode_ends.tolist() == [161, 279, 420, 579, 738]
    for key in ("observation.state", "action"):
        assert np.array_equal(b.root["data"][key][:], parquet_column(data, key))
        assert np.array_equal(a.root["data"][key][:], b.root["data"][key][:])
    diff = np.abs(b.root["data"]["observation.image"][:].astype(int)
                  - png_frames(data, "observation.image")).mean()
    print(f"AV1 crf 30 round trip: mean |pixel difference| {diff:.3f}")
    assert diff < 3
    task = pq.read_table(shared_data / IMAGES / "meta/tasks.parquet").to_pydict()["task"][0]
    assert b.attrs["sources"][0]["reader"]["episode_tasks"] == [[task]] * 5


def test_written_tables_follow_lerobots_layout(shared_data, round_trip):
    ours, theirs = round_trip / "lr", shared_data / VIDEO
    info = json.loads((ours / "meta/info.json").read_text())
    assert info["codebase_version"] == "v3.0" and info["total_frames"] == 738
    assert info["features"]["observation.image"]["info"]["video.codec"] == "av1"
    ref_data = pq.ParquetFile(theirs / "data/chunk-000/file-000.parquet")
    data = pq.ParquetFile(ours / "data/chunk-000/file-000.parquet")
    assert data.num_row_groups == 5  # one per episode, as LeRobot writes
    assert data.schema_arrow.field("action").type == ref_data.schema_arrow.field("action").type
    ref_eps = pq.read_schema(next((theirs / "meta/episodes").rglob("*.parquet"))).names
    eps = pq.read_schema(next((ours / "meta/episodes").rglob("*.parquet"))).names
    assert set(ref_eps) - set(eps) <= set()  # every column LeRobot writes
    stats = json.loads((ours / "meta/stats.json").read_text())
    assert set(stats["action"]) == {"min", "max", "mean", "std", "count", "q01", "q10", "q50",
                                    "q90", "q99"}
    assert np.array(stats["observation.image"]["mean"]).shape == (3, 1, 1)
    assert stats["action"]["count"] == [738]
    assert pq.read_table(ours / "meta/tasks.parquet").to_pydict()["task"] == \
        pq.read_table(shared_data / IMAGES / "meta/tasks.parquet").to_pydict()["task"]


def test_convert_takes_a_task_per_input_and_a_codec(tmp_path):
    """Two v2.1 inputs (H.264) to one LeRobot v3.0 dataset in HEVC, read back."""
    from sefa_data.convert import convert_to_lerobot

    truths = [write_v21(tmp_path / name, lengths=(6, 5), seed=seed)
              for seed, name in enumerate(("a", "b"))]
    summary = convert_to_lerobot([tmp_path / "a", tmp_path / "b"], tmp_path / "lr",
                                 IngestOptions(), ["first task", "second task"], codec="hevc")
    assert summary["episodes"] == 4 and summary["codec"] == "hevc"
    info = json.loads((tmp_path / "lr/meta/info.json").read_text())
    assert info["features"]["observation.images.cam"]["info"]["video.codec"] == "hevc"
    rec = read_lerobot(tmp_path / "lr")
    eps = list(rec.episodes)
    assert rec.meta["episode_tasks"] == [["first task"]] * 2 + [["second task"]] * 2
    expected = [t["state"][i] for t in truths for i in range(2)]
    frames = [t["frames"][i] for t in truths for i in range(2)]
    for ep, want, video in zip(eps, expected, frames):
        assert np.array_equal(ep.data["observation.state"], want)
        # two lossy generations (H.264 crf 10, then HEVC crf 30) on blocks of random colour;
        # a frame out of place would be off by about 85
        assert np.abs(ep.data["observation.images.cam"].astype(int) - video).mean() < 8
    assert not list(tmp_path.glob(".lr*"))  # the temporary store is gone


# ------------------------------------------------------------------ bad input


def fails(*args) -> str:
    r = sefa(*args)
    assert r.returncode == 1, r.stdout + r.stderr
    lines = r.stderr.strip().splitlines()
    assert "Traceback" not in r.stderr
    return lines[-1]


def test_bad_lerobot_inputs_are_one_line(tmp_path):
    cases = {
        "no_info": ({}, lambda r: (r / "meta/info.json").unlink(), "no meta/info.json"),
        "version": ({}, lambda r: (r / "meta/info.json").write_text(json.dumps(
            {**json.loads((r / "meta/info.json").read_text()), "codebase_version": "v9.9"})),
            "codebase_version 'v9.9'"),
        "truncated": ({}, lambda r: _truncate(r / "data/chunk-000/episode_000001.parquet"),
                      "episode_000001.parquet: unreadable parquet"),
        "no_video": ({}, lambda r: (r / "videos/chunk-000/observation.images.cam/episode_000001.mp4")
                     .unlink(), "episode_000001.mp4: observation.images.cam: missing video file"),
        "short_video": ({"video_short_by": 3}, None, "the video is shorter than its episode"),
        "counts": ({"length_lie": 10}, None, "frame counts disagree"),
        "nan": ({"nan_at": (1, 4)}, None, "observation.state: NaN or Inf value"),
        "grid": ({"timestamp_jump_at": (1, 5)}, None, "episode 1, frame 5"),
    }
    for name, (kw, damage, expected) in cases.items():
        root = tmp_path / name
        write_v21(root, **kw)
        if damage:
            damage(root)
        out = tmp_path / f"{name}.zarr"
        if name == "no_info":  # the command line: exit 1, one line, no traceback
            line = fails("ingest", root, "--out", out)
        else:
            with pytest.raises(SefaInputError) as e:
                ingest([root], out, IngestOptions())
            line = e.value.line()
        print(f"{name}: {line}")
        assert expected in line, (name, line)
        assert not (tmp_path / f"{name}.zarr").exists()


def _truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[:200])


def test_timestamp_off_the_grid_names_episode_frame_and_step(tmp_path):
    write_v21(tmp_path / "d", timestamp_jump_at=(1, 5))
    with pytest.raises(SefaInputError) as e:
        list(read_lerobot(tmp_path / "d").episodes)
    assert "a step of 150.000 ms where 10 fps needs 100.000 ms (off by +50.000 ms" in e.value.line()
    assert e.value.where == "episode 1, frame 5"


def test_convert_refuses_an_existing_folder_and_leaves_nothing_half_written(tmp_path, monkeypatch):
    write_v21(tmp_path / "v21")
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep").write_text("x")
    assert "already exists" in fails("convert", tmp_path / "v21", "--out", out)
    assert [p.name for p in out.iterdir()] == ["keep"]
    # a conversion that fails midway (here: the video encoder, after the first episode) leaves
    # neither the folder nor its temporary build
    from sefa_data.lerobot import writer as lerobot_writer
    from sefa_data.convert import convert_to_lerobot

    calls = []
    real = lerobot_writer._Video.write

    def failing(self, frames):
        calls.append(1)
        if len(calls) > 1:
            raise OSError(28, "No space left on device")
        real(self, frames)

    monkeypatch.setattr(lerobot_writer._Video, "write", failing)
    with pytest.raises(OSError):
        convert_to_lerobot([tmp_path / "v21"], tmp_path / "new", IngestOptions(), [])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out", "v21"]


def test_inspect_shows_the_datasets_statistics(shared_data, tmp_path):
    """`sefa inspect` on a LeRobot folder showed features and tasks but no statistics. Now each
    numeric feature's own statistics: meta/stats.json's (LeRobot's aggregate) where the dataset
    has one; else its episodes' combined (a copy without stats.json), which here agree with the
    values in the data parquet itself."""
    root = shared_data / IMAGES
    recorded = json.loads((root / "meta/stats.json").read_text())
    s = inspect_lerobot(root)
    assert s["stats_source"] == "meta/stats.json"
    for key in ("observation.state", "action"):
        assert s["features"][key]["stats"]["mean"] == recorded[key]["mean"]
        assert s["features"][key]["stats"]["q99"] == recorded[key]["q99"]
    assert s["features"]["observation.image"]["stats"] is None  # cameras: not in the table
    r = sefa("inspect", root)
    assert r.returncode == 0, r.stderr
    text = " ".join(r.stdout.split())
    assert "per-dimension statistics (the dataset's: meta/stats.json)" in text
    assert f"{recorded['observation.state']['max'][0]:.4g}" in text

    copy = tmp_path / "no_stats"
    copy.mkdir()
    for part in ("data", "videos"):
        if (root / part).exists():
            (copy / part).symlink_to(root / part)
    (copy / "meta").mkdir()
    for item in (root / "meta").iterdir():
        if item.name != "stats.json":
            (copy / "meta" / item.name).symlink_to(item)
    s = inspect_lerobot(copy)
    assert s["stats_source"] == "the episodes' statistics"
    table = pq.read_table(next((root / "data").glob("*/*.parquet")))
    for key in ("observation.state", "action"):
        values = parquet_column(table, key).astype(np.float64)
        got = s["features"][key]["stats"]
        np.testing.assert_allclose(got["min"], values.min(0), rtol=1e-6)
        np.testing.assert_allclose(got["max"], values.max(0), rtol=1e-6)
        np.testing.assert_allclose(got["mean"], values.mean(0), rtol=1e-5)
