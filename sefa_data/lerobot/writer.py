"""Write a sefa store as a LeRobot v3.0 dataset, the files LeRobot 0.6.1's own writer makes.

``meta/info.json``, ``meta/stats.json`` (LeRobot's statistics), ``meta/tasks.parquet``,
``meta/episodes/chunk-000/file-000.parquet`` (one row per episode: where its rows and video
span are, its tasks and statistics), ``data/chunk-CCC/file-FFF.parquet`` (one row group per
episode, many episodes per file) and ``videos/<key>/chunk-CCC/file-FFF.mp4`` (episodes one
after the other, AV1 by default). Images become video features; low-dim keys keep their dtype
(a key of more than one dimension is written flattened: LeRobot's policies take vectors).
LeRobot's own columns are added: ``timestamp = frame_index / fps``, ``frame_index``,
``episode_index``, ``index``, ``task_index``.

The dataset is built in a temporary folder beside the target (``.NAME.tmp-PID``: the next
conversion to that target removes it once that process is dead) and renamed into place when
complete, so a failed or killed conversion leaves no folder that LeRobot would half-load. The
rename never replaces anything: a target that appeared meanwhile is left as it is and the
conversion fails (`atomic.publish_new_dir`). Videos are encoded in child processes under a
watchdog (`video_encoder`).

Fault points (store.journal.fault_point): ``convert.episode`` after each episode is written,
``convert.written`` when the dataset is complete in its temporary folder, not yet published.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from sefa_data import atomic
from sefa_data.errors import SefaInputError
from sefa_data.lerobot.stats import aggregate, image_episode_stats, lowdim_episode_stats, to_json
from sefa_data.store.journal import fault_point
from sefa_data.lerobot.video_encoder import CODECS, DEFAULT_STALL_TIMEOUT, VideoProcess
from sefa_data.store.zarr_store import EpisodeStore

CODEBASE_VERSION = "v3.0"
CHUNKS_SIZE = 1000  # files per chunk folder (LeRobot's default)
DATA_FILE_MB = 100  # LeRobot starts a new data file past about this size
VIDEO_FILE_MB = 200  # ... and a new video file past this one
_DATA_PATH = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
_VIDEO_PATH = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"


def write_lerobot(store_path: str | Path, out: str | Path, tasks: list[str],
                  codec: str = "av1", robot_type: str | None = None,
                  progress: Callable[[int, int], None] = lambda done, total: None,
                  stall_timeout: float = DEFAULT_STALL_TIMEOUT) -> dict:
    """Write every episode of the store; `tasks` holds one task string per episode."""
    out = Path(out)
    check_new_target(out)
    if codec not in CODECS:
        raise SefaInputError(f"unknown codec {codec!r} (choose {', '.join(CODECS)})", key="--codec")
    store = EpisodeStore.open(store_path)
    robot_type = robot_type or recorded_robot_type(store)
    if len(tasks) != store.n_episodes:
        raise ValueError(f"{len(tasks)} tasks for {store.n_episodes} episodes")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = atomic.owned_name(out, "tmp")
    atomic.remove_temporary(tmp)
    try:
        summary = _Writer(store, tmp, tasks, codec, robot_type, stall_timeout).run(progress)
        fault_point("convert.written")
        try:
            atomic.publish_new_dir(tmp, out)
        except FileExistsError:
            raise SefaInputError("appeared while the conversion ran; it was left as it is and "
                                 "nothing was written (choose another --out, or remove it and "
                                 "convert again)", file=str(out)) from None
    except BaseException:
        atomic.remove_temporary(tmp)
        raise
    return {**summary, "path": str(out)}


def recorded_robot_type(store: EpisodeStore) -> str | None:
    """The robot_type the store's LeRobot sources recorded, when they agree on one."""
    found = {(s.get("reader") or {}).get("robot_type") for s in store.attrs.get("sources", [])}
    found.discard(None)
    return found.pop() if len(found) == 1 and isinstance(next(iter(found)), str) else None


TEMPORARIES = ("tmp", "store")  # .NAME.KIND-PID beside --out: the build, the ingested store


def check_new_target(out: Path) -> None:
    """`--out` must be a new name in a folder: anything already there (a folder, a file, a
    symlink, even a dangling one) or a parent that is not a folder is one line naming the
    user's path. Leftovers of a killed conversion to the same target are removed first."""
    atomic.remove_dead_temporaries(out, TEMPORARIES)
    if os.path.islink(out) and not out.exists():
        raise SefaInputError(f"is a dangling symlink (to {os.readlink(out)}); a conversion "
                             "writes a new folder: choose another --out or remove the link",
                             file=str(out))
    if out.exists():
        raise SefaInputError("already exists (a conversion never writes into an existing folder; "
                             "choose another --out or remove it)", file=str(out))
    for parent in out.parents:
        if parent.exists():
            if not parent.is_dir():
                raise SefaInputError(f"{parent} is not a folder, so --out cannot be made in it",
                                     file=str(out))
            if not os.access(parent, os.W_OK | os.X_OK):
                raise SefaInputError(f"{parent} is not writable, so --out cannot be made in it",
                                     file=str(out))
            break


@dataclass
class _FileSlot:
    """The chunk and file a stream of episodes is being written to."""

    chunk: int = 0
    file: int = 0

    def advance(self) -> None:
        self.file += 1
        if self.file >= CHUNKS_SIZE:
            self.chunk, self.file = self.chunk + 1, 0


@dataclass
class _Video:
    """One video file of one key: episodes are appended one after the other, encoded by a child
    process under a watchdog (`video_encoder.VideoProcess`)."""

    path: Path
    key: str
    codec: str
    fps: float
    stall_timeout: float = DEFAULT_STALL_TIMEOUT
    encoder: VideoProcess | None = None
    episode: int = 0  # the episode being written, named if the encoder stalls

    @property
    def frames(self) -> int:  # frames written to this file so far
        return self.encoder.frames if self.encoder else 0

    @property
    def bytes(self) -> int:  # encoded bytes so far (the encoder holds frames: the file lags)
        return self.encoder.bytes if self.encoder else 0

    def write(self, frames: np.ndarray) -> None:
        if frames.shape[-1] != 3:
            raise SefaInputError(f"{frames.shape[-1]} channels: a LeRobot video feature is RGB "
                                 "(3 channels)", key=self.key)
        if frames.dtype != np.uint8:  # what PyAV's rgb24 takes; never cast (values would wrap)
            raise SefaInputError(f"{frames.dtype} frames: a LeRobot video feature is uint8 RGB",
                                 key=self.key)
        if self.encoder is None:
            height, width = frames.shape[1:3]
            if height % 2 or width % 2:
                raise SefaInputError(f"frames of {height}x{width}: yuv420p video needs an even "
                                     "height and width", key=self.key)
            if self.codec == "hevc" and min(height, width) < 64:
                # x265 corrupts the heap (the process aborts) on frames smaller than its
                # 64-pixel coding unit; seen with PyAV 18's libx265 on 48x32 frames
                raise SefaInputError(f"frames of {height}x{width}: HEVC (x265) needs at least "
                                     "64x64; use --codec av1 or h264", key=self.key)
            self.encoder = VideoProcess(self.path, self.key, self.codec, self.fps,
                                        self.stall_timeout)
        self.encoder.write(frames, f"episode {self.episode} ({len(frames)} frames)")

    def close(self) -> None:
        if self.encoder is not None:
            self.encoder.close()

    def kill(self) -> None:
        if self.encoder is not None:
            self.encoder.kill()


@dataclass
class _Writer:
    store: EpisodeStore
    root: Path
    tasks: list[str]
    codec: str
    robot_type: str | None
    stall_timeout: float = DEFAULT_STALL_TIMEOUT
    rows: list[dict] = field(default_factory=list)  # the episodes table
    stats: list[dict] = field(default_factory=list)  # per episode: feature -> stats

    def run(self, progress: Callable[[int, int], None]) -> dict:
        features = self.store.attrs["features"]
        self.image_keys = [k for k, f in features.items() if f["type"] == "image"]
        self.lowdim_keys = [k for k, f in features.items() if f["type"] != "image"]
        self.task_list = list(dict.fromkeys(self.tasks))
        self.fps = self.store.fps
        data_slot, self.data_bytes, self.parquet = _FileSlot(), 0, None
        video_slots = {k: _FileSlot() for k in self.image_keys}
        self.videos = {k: self._video(k, video_slots[k]) for k in self.image_keys}
        index, ok = 0, False
        try:
            for i in range(self.store.n_episodes):
                episode = self.store.get_episode(i)
                n = len(next(iter(episode.values())))
                if self.data_bytes > DATA_FILE_MB << 20:
                    self._close_parquet()
                    data_slot.advance()
                row = self._write_data(i, episode, n, index, data_slot)
                for k in self.image_keys:
                    row.update(self._write_video(i, k, episode[k], video_slots))
                self.rows.append(row)
                index += n
                fault_point("convert.episode")
                progress(i + 1, self.store.n_episodes)
            ok = True
        finally:
            self._close_parquet()
            for v in self.videos.values():
                # an error or an interrupt stops the encoders at once: a flush may be what hangs
                v.close() if ok else v.kill()
        self._write_meta(index)
        return {"episodes": self.store.n_episodes, "frames": index, "tasks": len(self.task_list),
                "videos": self.image_keys, "codec": self.codec if self.image_keys else None}

    # ---- data parquet

    def _write_data(self, i: int, episode: dict, n: int, index: int, slot: _FileSlot) -> dict:
        import pyarrow as pa
        import pyarrow.parquet as pq

        task = self.task_list.index(self.tasks[i])
        frame_index = np.arange(n, dtype=np.int64)
        columns = {k: _column(episode[k]) for k in self.lowdim_keys}
        columns |= {"timestamp": pa.array((frame_index / self.fps).astype(np.float32)),
                    "frame_index": pa.array(frame_index),
                    "episode_index": pa.array(np.full(n, i, np.int64)),
                    "index": pa.array(np.arange(index, index + n, dtype=np.int64)),
                    "task_index": pa.array(np.full(n, task, np.int64))}
        table = pa.table(columns).replace_schema_metadata({"huggingface": json.dumps(
            {"info": {"features": self._hf_features()}})})
        if self.parquet is None:
            path = self.root / _DATA_PATH.format(chunk_index=slot.chunk, file_index=slot.file)
            path.parent.mkdir(parents=True, exist_ok=True)
            self.parquet = pq.ParquetWriter(path, table.schema)
        self.parquet.write_table(table)
        self.data_bytes += table.nbytes
        stats = {k: lowdim_episode_stats(episode[k]) for k in self.lowdim_keys}
        stats |= {k: lowdim_episode_stats(columns[k].to_numpy()) for k in
                  ("timestamp", "frame_index", "episode_index", "index", "task_index")}
        stats |= {k: image_episode_stats(episode[k]) for k in self.image_keys}
        self.stats.append(stats)
        row = {"episode_index": i, "tasks": [self.tasks[i]], "length": n,
               "data/chunk_index": slot.chunk, "data/file_index": slot.file,
               "dataset_from_index": index, "dataset_to_index": index + n}
        return row

    def _close_parquet(self) -> None:
        if self.parquet is not None:
            self.parquet.close()
            self.parquet, self.data_bytes = None, 0

    def _hf_features(self) -> dict:
        out = {}
        for k in self.lowdim_keys:
            f = self.store.attrs["features"][k]
            size = int(np.prod(f["shape"]))
            value = {"dtype": f["dtype"], "_type": "Value"}
            out[k] = value if size == 1 else {"feature": value, "length": size, "_type": "List"}
        out |= {"timestamp": {"dtype": "float32", "_type": "Value"}}
        out |= {k: {"dtype": "int64", "_type": "Value"}
                for k in ("frame_index", "episode_index", "index", "task_index")}
        return out

    # ---- videos

    def _video(self, key: str, slot: _FileSlot) -> _Video:
        path = self.root / _VIDEO_PATH.format(video_key=key, chunk_index=slot.chunk,
                                              file_index=slot.file)
        return _Video(path, key, self.codec, self.fps, self.stall_timeout)

    def _write_video(self, i: int, key: str, frames: np.ndarray,
                     slots: dict[str, _FileSlot]) -> dict:
        video = self.videos[key]
        if video.bytes > VIDEO_FILE_MB << 20:
            video.close()
            slots[key].advance()
            video = self.videos[key] = self._video(key, slots[key])
        start = video.frames / self.fps
        video.episode = i
        video.write(frames)
        return {f"videos/{key}/chunk_index": slots[key].chunk,
                f"videos/{key}/file_index": slots[key].file,
                f"videos/{key}/from_timestamp": start,
                f"videos/{key}/to_timestamp": video.frames / self.fps}

    # ---- metadata

    def _write_meta(self, frames: int) -> None:
        import pyarrow as pa
        import pyarrow.parquet as pq

        meta = self.root / "meta"
        (meta / "episodes" / "chunk-000").mkdir(parents=True, exist_ok=True)
        keys = list(self.stats[0])
        for row, stats in zip(self.rows, self.stats):
            for k in keys:
                row.update({f"stats/{k}/{s}": np.asarray(v).tolist() for s, v in stats[k].items()})
            row.update({"meta/episodes/chunk_index": 0, "meta/episodes/file_index": 0})
        pq.write_table(pa.Table.from_pylist(self.rows),
                       meta / "episodes" / "chunk-000" / "file-000.parquet")
        tasks = pa.table({"task_index": pa.array(range(len(self.task_list)), pa.int64()),
                          "task": pa.array(self.task_list, pa.string())})
        # LeRobot reads the table with pandas, the task string as its index
        pq.write_table(tasks.replace_schema_metadata({"pandas": json.dumps(_PANDAS_TASKS)}),
                       meta / "tasks.parquet")
        stats = {k: to_json(aggregate([s[k] for s in self.stats])) for k in keys}
        atomic.write_json(meta / "stats.json", stats, indent=4)
        atomic.write_json(meta / "info.json", self._info(frames), indent=4)

    def _info(self, frames: int) -> dict:
        features = {}
        for k in self.image_keys:
            h, w, c = self.store.attrs["features"][k]["shape"]
            features[k] = {"dtype": "video", "shape": [h, w, c],
                           "names": ["height", "width", "channel"], "info": self._video_info(h, w, c)}
        for k in self.lowdim_keys:
            f = self.store.attrs["features"][k]
            features[k] = {"dtype": f["dtype"], "shape": [int(np.prod(f["shape"]))],
                           "names": f.get("names")}
        features |= {"timestamp": {"dtype": "float32", "shape": [1], "names": None}}
        features |= {k: {"dtype": "int64", "shape": [1], "names": None}
                     for k in ("frame_index", "episode_index", "index", "task_index")}
        n = len(self.rows)
        return {"codebase_version": CODEBASE_VERSION, "fps": _fps_value(self.fps),
                "features": features, "total_episodes": n, "total_frames": frames,
                "total_tasks": len(self.task_list), "chunks_size": CHUNKS_SIZE,
                "data_files_size_in_mb": DATA_FILE_MB, "video_files_size_in_mb": VIDEO_FILE_MB,
                "data_path": _DATA_PATH, "video_path": _VIDEO_PATH if self.image_keys else None,
                "robot_type": self.robot_type, "splits": {"train": f"0:{n}"}}

    def _video_info(self, h: int, w: int, c: int) -> dict:
        _, name, options = CODECS[self.codec]
        return {"video.height": h, "video.width": w, "video.codec": name,
                "video.pix_fmt": "yuv420p", "video.fps": _fps_value(self.fps), "video.channels": c,
                "has_audio": False, "video.g": int(options["g"]), "video.crf": int(options["crf"]),
                "video.video_backend": "pyav", "is_depth_map": False}


def _fps_value(fps: float) -> int | float:
    return int(fps) if float(fps).is_integer() else fps


def _column(values: np.ndarray):
    """A low-dim key as LeRobot stores it: a scalar column for one value per frame, else a
    fixed-size list column."""
    import pyarrow as pa

    flat = np.ascontiguousarray(values.reshape(len(values), -1))
    if flat.shape[1] == 1:
        return pa.array(flat[:, 0])
    return pa.FixedSizeListArray.from_arrays(pa.array(flat.reshape(-1)), flat.shape[1])


_PANDAS_TASKS = {
    "index_columns": ["task"],
    "column_indexes": [{"name": None, "field_name": None, "pandas_type": "unicode",
                        "numpy_type": "object", "metadata": {"encoding": "UTF-8"}}],
    "columns": [{"name": "task_index", "field_name": "task_index", "pandas_type": "int64",
                 "numpy_type": "int64", "metadata": None},
                {"name": "task", "field_name": "task", "pandas_type": "unicode",
                 "numpy_type": "object", "metadata": None}],
    "attributes": {}, "creator": {"library": "pyarrow"}, "pandas_version": "2.3.3"}
