"""A small LeRobot v3.0 dataset written with the real writers (pyarrow, PyAV) by the layout
LeRobot 0.6.1's own writer produces, for the cases no real file covers: an action declared
with a leading axis of 1 (`[1, 2]`), several cameras, uploads that lack their files.

The layout, as `LeRobotDataset.create` / `save_episode` / `finalize` write it (checked against
a dataset LeRobot 0.6.1 wrote with an action of shape (1, 2)): every episode's rows in one data
parquet (a feature of shape [1, 2] is a list of lists, one inner list of two values, as
`datasets.Array2D` stores it), every episode's frames of a camera in one video file (episode e
starts at `videos/KEY/from_timestamp`), an episodes table with LeRobot's columns and
per-episode statistics flattened to one list per statistic, and meta/tasks.parquet as pandas
writes a DataFrame indexed by task (tests/data/lerobot_tasks, written by pandas itself).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

TASKS = Path(__file__).resolve().parent / "data" / "lerobot_tasks" / "tasks_unnamed_index.parquet"
TASK = "Push the T-shaped block onto the target."  # task_index 0 of that table
DATA = "data/chunk-000/file-000.parquet"
EPISODES = "meta/episodes/chunk-000/file-000.parquet"


def video_file(root: Path, key: str) -> Path:
    return root / f"videos/{key}/chunk-000/file-000.mp4"


def _nested(values: np.ndarray) -> pa.Array:
    """(rows, *shape) as pyarrow lists nested as deep as the shape (Array2D: list of lists)."""
    arr = pa.array(values.reshape(-1))
    for size in reversed(values.shape[1:]):
        arr = pa.ListArray.from_arrays(pa.array(np.arange(0, len(arr) + 1, size, dtype=np.int32)),
                                       arr)
    return arr


def write_v30(root: Path, lengths=(5, 4), fps: int = 10, action_shape=(2,),
              cameras=("observation.images.cam",), seed: int = 0,
              action: np.ndarray | None = None) -> dict:
    """The dataset at `root`; returns what it holds: {"state": (N, 3), "action": (N,
    *action_shape), "ends": [...], camera: (N, 64, 96, 3) uint8 frames}; `action`: its values
    instead of random ones."""
    rng = np.random.default_rng(seed)
    n = sum(lengths)
    state = rng.normal(size=(n, 3)).astype(np.float32)
    action = rng.normal(size=(n, *action_shape)).astype(np.float32) if action is None \
        else np.asarray(action, np.float32)
    episode = np.repeat(np.arange(len(lengths)), lengths)
    frame = np.concatenate([np.arange(k) for k in lengths])
    (root / "meta/episodes/chunk-000").mkdir(parents=True)
    (root / "data/chunk-000").mkdir(parents=True)
    columns = {"observation.state": pa.FixedSizeListArray.from_arrays(pa.array(state.ravel()), 3),
               "action": _nested(action) if len(action_shape) > 1 else
               pa.FixedSizeListArray.from_arrays(pa.array(action.ravel()), action_shape[0]),
               "timestamp": pa.array((frame / fps).astype(np.float32)),
               "frame_index": pa.array(frame.astype(np.int64)),
               "episode_index": pa.array(episode.astype(np.int64)),
               "index": pa.array(np.arange(n, dtype=np.int64)),
               "task_index": pa.array(np.zeros(n, np.int64))}
    pq.write_table(pa.table(columns), root / DATA)
    truth = {"state": state, "action": action, "ends": np.cumsum(lengths).tolist()}
    for key in cameras:
        truth[key] = _write_video(video_file(root, key), n, fps, rng)
    starts = np.r_[0, np.cumsum(lengths)[:-1]]
    rows = []
    for e, (start, length) in enumerate(zip(starts, lengths)):
        row = {"episode_index": e, "tasks": [TASK], "length": int(length),
               "data/chunk_index": 0, "data/file_index": 0,
               "dataset_from_index": int(start), "dataset_to_index": int(start + length)}
        for key in cameras:
            row |= {f"videos/{key}/chunk_index": 0, f"videos/{key}/file_index": 0,
                    f"videos/{key}/from_timestamp": float(start / fps),
                    f"videos/{key}/to_timestamp": float((start + length) / fps)}
        for key, values in (("observation.state", state), ("action", action)):
            x = values[start:start + length].reshape(length, -1).astype(np.float64)
            row |= {f"stats/{key}/min": x.min(0).tolist(), f"stats/{key}/max": x.max(0).tolist(),
                    f"stats/{key}/mean": x.mean(0).tolist()}
        rows.append(row)
    pq.write_table(pa.Table.from_pylist(rows), root / EPISODES)
    shutil.copy(TASKS, root / "meta/tasks.parquet")
    features = {
        "observation.state": {"dtype": "float32", "shape": [3], "names": ["x", "y", "z"]},
        "action": {"dtype": "float32", "shape": list(action_shape), "names": None},
        **{key: {"dtype": "video", "shape": [64, 96, 3], "names": ["height", "width", "channels"],
                 "info": {"video.fps": fps, "video.height": 64, "video.width": 96,
                          "video.channels": 3, "video.codec": "h264",
                          "video.pix_fmt": "yuv420p", "video.is_depth_map": False,
                          "has_audio": False}} for key in cameras},
        "timestamp": {"dtype": "float32", "shape": [1], "names": None},
        **{k: {"dtype": "int64", "shape": [1], "names": None}
           for k in ("frame_index", "episode_index", "index", "task_index")}}
    info = {"codebase_version": "v3.0", "robot_type": None, "total_episodes": len(lengths),
            "total_frames": n, "total_tasks": 1, "chunks_size": 1000,
            "data_files_size_in_mb": 100, "video_files_size_in_mb": 200, "fps": fps,
            "splits": {"train": f"0:{len(lengths)}"},
            "data_path": "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet",
            "video_path": ("videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
                           if cameras else None),
            "features": features}
    (root / "meta/info.json").write_text(json.dumps(info, indent=4))
    return truth


def _write_video(path: Path, n: int, fps: int, rng) -> np.ndarray:
    """n frames of coloured 16-pixel blocks, H.264 (crf 10), one frame per 1/fps."""
    import av

    frames = rng.integers(0, 256, size=(n, 4, 6, 3), dtype=np.uint8).repeat(16, 1).repeat(16, 2)
    path.parent.mkdir(parents=True, exist_ok=True)
    with av.open(str(path), "w") as c:
        s = c.add_stream("h264", rate=fps, options={"crf": "10", "g": "2"})
        s.width, s.height, s.pix_fmt = 96, 64, "yuv420p"
        for i, img in enumerate(frames):
            f = av.VideoFrame.from_ndarray(img, format="rgb24")
            f.pts = i
            c.mux(s.encode(f))
        c.mux(s.encode(None))
    return frames


def lfs_pointer(path: Path) -> None:
    """Replace `path` by the Git LFS pointer a clone without `git lfs pull` holds in its place
    (the spec's three lines: https://github.com/git-lfs/git-lfs/blob/main/docs/spec.md)."""
    import hashlib

    data = path.read_bytes()
    path.write_text("version https://git-lfs.github.com/spec/v1\n"
                    f"oid sha256:{hashlib.sha256(data).hexdigest()}\nsize {len(data)}\n")
