"""Read a local LeRobot dataset (v3.0 or v2.1) as episodes for the store.

Feature names are kept (``observation.state``, ``observation.images.*``, ``action``). Low-dim
columns become arrays of the feature's dtype and shape, exactly the parquet's values. Image
features (PNG or JPEG bytes in the parquet) are decoded with Pillow; video features (AV1, H.264,
HEVC) with PyAV, LeRobot's own fallback decoder, at each frame's timestamp as LeRobot does:
the frame nearest to ``from_timestamp + timestamp``, which must lie within LeRobot's tolerance
(1e-4 s). Data is read one parquet row group at a time and videos are decoded as a stream,
one episode's frames at a time, so memory stays at about one episode whatever the file sizes.

Timestamps off the fps grid (a step between two frames that is not 1/fps within the
tolerance: LeRobot's most reported loading error) are refused with a line naming the episode,
the frame and the size of the step, not resampled: in a LeRobot dataset the rows are the frames
and the video is indexed by their timestamps, so a broken step means frames were dropped or
doubled when it was recorded; holding values across it would make up frames that LeRobot's own
loader refuses to load. A timestamp that is not finite is refused the same way.

info.json is checked like a topic map (`lerobot.layout`): a dtype that would change the
parquet's values (a float action declared int8: 233.0 would read -23) is refused unless
`allow_lossy_cast`, as the topic map's own option; an image's size must be the one info.json
gives. What is read is compared with the dataset's own per-episode statistics where it has
them (min, max and mean of each low-dim feature): parquet has no checksum of its pages, so a
flipped bit would otherwise be ingested as a value of 1e21.
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from sefa_data.episode import Episode, Recording
from sefa_data.errors import SefaInputError, clip
from sefa_data.lerobot.files import is_lfs_pointer, lfs_error, parquet_error
from sefa_data.lerobot.layout import (EpisodeRef, Layout, check_referenced_files, load_layout,
                                      referenced_files)
from sefa_data.validate import lossy_cast

TOLERANCE_S = 1e-4  # LeRobot's tolerance_s default
_LOWDIM = {"float16", "float32", "float64", "int8", "int16", "int32", "int64", "uint8", "uint16",
           "uint32", "uint64", "bool"}


def read_lerobot(path: str | Path, keys: list[str] | None = None,
                 episodes: list[int] | None = None,
                 renames: dict[str, str] | None = None,
                 allow_lossy_cast: bool = False, check_stats: bool = True) -> Recording:
    """`keys`: only these features (default all); `episodes`: only these episode_index values
    (default all), as LeRobotDataset's own `episodes=` argument; `renames`: feature -> the key
    it is stored under; `allow_lossy_cast`: apply info.json's dtypes even where they change
    values; `check_stats`: compare what is read with the dataset's per-episode statistics."""
    layout = load_layout(path)
    readable, skipped = _readable(layout.features)
    for k in keys or []:
        if k not in layout.features:
            raise SefaInputError(f"no such feature (features: {', '.join(layout.features)})",
                                 file=str(Path(path) / "meta" / "info.json"), key=k)
    if keys is not None:
        skipped |= {k: "not among the --key choices" for k in readable if k not in keys}
    keys = [k for k in readable if keys is None or k in keys]
    for k in keys:
        if k in layout.unplaced:
            raise layout.unplaced_error(k, [o for o in keys if o not in layout.unplaced])
    if episodes is not None:
        missing = sorted(set(episodes) - {e.index for e in layout.episodes})
        if missing:
            raise SefaInputError(f"no episode_index {missing[0]}", file=str(path))
        layout.episodes = [e for e in layout.episodes if e.index in set(episodes)]
    meta = {"format": "lerobot", "codebase_version": layout.version, "fps": layout.fps,
            "robot_type": layout.info.get("robot_type"), "tasks": layout.tasks,
            "episode_tasks": [e.tasks for e in layout.episodes],
            "episode_index": [e.index for e in layout.episodes],
            "features": {k: layout.features[k] for k in keys}, "skipped": skipped}
    renames = dict(renames or {})
    for old in renames:
        if old not in layout.features:
            raise SefaInputError("--rename names no feature of this dataset",
                                 file=str(Path(path) / "meta" / "info.json"), key=old)
    # every file the chosen episodes and keys need, before the first frame is decoded
    check_referenced_files(layout, [k for k in keys if layout.features[k]["dtype"] == "video"])
    if not check_stats:
        for ep in layout.episodes:
            ep.stats = {}
    return Recording(meta=meta, episodes=_renamed(_episodes(layout, keys, allow_lossy_cast),
                                                  renames))


def _renamed(episodes: Iterator[Episode], renames: dict[str, str]) -> Iterator[Episode]:
    for ep in episodes:
        if renames:
            ep.data = {renames.get(k, k): v for k, v in ep.data.items()}
            ep.names = {renames.get(k, k): v for k, v in ep.names.items()}
        yield ep


def _readable(features: dict) -> tuple[list[str], dict[str, str]]:
    keys, skipped = [], {}
    for k, f in features.items():
        if f.get("dtype") in ("video", "image") or f.get("dtype") in _LOWDIM:
            keys.append(k)
        else:
            skipped[k] = f"dtype {f.get('dtype')!r} is not numeric, an image or a video"
    return keys, skipped


def _episodes(layout: Layout, keys: list[str], allow_lossy_cast: bool = False
              ) -> Iterator[Episode]:
    names = {k: n for k in keys if (n := value_names(layout.features[k])) is not None}
    rows = _RowStream(every_row=len(layout.episodes) == int(layout.info.get(
        "total_episodes", len(layout.episodes))))
    videos: dict[str, _VideoStream] = {}
    try:
        for ep in layout.episodes:
            table = rows.take(ep)
            data, ts = _lowdim_and_images(table, ep, layout, keys, allow_lossy_cast)
            for k in keys:
                if layout.features[k]["dtype"] == "video":
                    file, start = ep.videos[k]
                    stream = videos.get(k)
                    if stream is None or stream.file != file:
                        if stream is not None:
                            stream.close()
                        stream = videos[k] = _VideoStream(file, k)
                    data[k] = stream.frames(start + ts, ep)
                    check_image_size(data[k], layout.features[k], str(file), k, ep)
            yield Episode(data=data, source=str(ep.data_file), label=f"episode_index {ep.index}",
                          names=names)
        rows.finish()
    finally:
        for stream in videos.values():
            stream.close()


def value_names(feature: dict) -> list[str] | None:
    """One name per value of a low-dim feature, from LeRobot's `names` when it has one per
    value: a list, a dict holding one list (as {"motors": [...]}), or lists nested in the
    feature's shape or in one more list (as Unitree writes them, [[...]]), read in order."""
    names = feature.get("names")
    if isinstance(names, dict) and len(names) == 1:
        names = next(iter(names.values()))
    size = int(np.prod(feature.get("shape") or [1]))
    if feature.get("dtype") in ("video", "image") or not isinstance(names, list):
        return None
    flat = _flat_strings(names)
    return flat if flat is not None and len(flat) == size else None


def _flat_strings(names: list) -> list[str] | None:
    out = []
    for n in names:
        if isinstance(n, str):
            out.append(n)
        elif isinstance(n, list) and (inner := _flat_strings(n)) is not None:
            out += inner
        else:
            return None
    return out


def _timestamps(table) -> np.ndarray:
    return np.asarray(table.column("timestamp").to_numpy(), np.float64)


class _RowStream:
    """The data parquet files' rows, one row group at a time, handed out episode by episode.

    With `every_row`, every row of a file must belong to an episode of the table."""

    def __init__(self, every_row: bool = True):
        self.every_row = every_row
        self.file: Path | None = None
        self.parquet = None
        self.group = 0
        self.position = 0  # the file's row at the start of `pending`
        self.pending = None  # rows read but not yet handed out

    def take(self, ep: EpisodeRef):
        import pyarrow as pa

        if ep.data_file != self.file or ep.start < self.position:
            self.finish()
            self._open(ep.data_file)
        self._skip_to(ep)
        parts, have = [], 0
        while have < ep.length:
            if self.pending is None or self.pending.num_rows == 0:
                self.pending = self._next_group(ep)
            part = self.pending.slice(0, ep.length - have)
            self.pending = self.pending.slice(part.num_rows)
            self.position += part.num_rows
            parts.append(part)
            have += part.num_rows
        table = pa.concat_tables(parts) if len(parts) > 1 else parts[0]
        _check_rows(table, ep)
        return table

    def _skip_to(self, ep: EpisodeRef) -> None:
        """Pass over rows of episodes not asked for (whole row groups unread)."""
        if ep.start > self.position and self.every_row:
            raise SefaInputError(f"episode {ep.index} starts at row {ep.start}, after row "
                                 f"{self.position} where the previous one ended", file=str(self.file))
        while ep.start > self.position:
            if self.pending is None or self.pending.num_rows == 0:
                size = self.parquet.metadata.row_group(self.group).num_rows \
                    if self.group < self.parquet.num_row_groups else 0
                if size and self.position + size <= ep.start:
                    self.group, self.position = self.group + 1, self.position + size
                    continue
                self.pending = self._next_group(ep)
            n = min(self.pending.num_rows, ep.start - self.position)
            self.pending = self.pending.slice(n)
            self.position += n

    def finish(self) -> None:
        """Every row of the open file must belong to a listed episode."""
        if self.parquet is None:
            return
        extra = (self.pending.num_rows if self.pending is not None else 0) + sum(
            self.parquet.metadata.row_group(g).num_rows
            for g in range(self.group, self.parquet.num_row_groups))
        if extra and self.every_row:
            raise SefaInputError(f"{extra} rows more than the episodes table gives this file "
                                 "(frame counts disagree between the tables)", file=str(self.file))
        self.parquet = None

    def _open(self, file: Path) -> None:
        import pyarrow as pa
        import pyarrow.parquet as pq

        if not file.is_file():
            raise SefaInputError("missing (the episodes table points to it)", file=str(file))
        try:
            self.parquet = pq.ParquetFile(file)
        except (pa.ArrowException, OSError) as e:
            raise parquet_error(file, e) from None
        self.file, self.group, self.position, self.pending = file, 0, 0, None

    def _next_group(self, ep: EpisodeRef):
        import pyarrow as pa

        if self.group >= self.parquet.num_row_groups:
            raise SefaInputError(f"the file ends before episode {ep.index}'s {ep.length} frames "
                                 "(frame counts disagree between the tables)", file=str(self.file))
        try:
            group = self.parquet.read_row_group(self.group)
        except (pa.ArrowException, OSError) as e:
            raise SefaInputError(f"unreadable row group {self.group} ({clip(str(e), 120)})",
                                 file=str(self.file)) from None
        self.group += 1
        return group


def _check_rows(table, ep: EpisodeRef) -> None:
    file = str(ep.data_file)
    for col in ("episode_index", "frame_index", "timestamp"):
        if col not in table.column_names:
            raise SefaInputError("column missing", file=file, key=col)
    episode = table.column("episode_index").to_numpy()
    if (episode != ep.index).any():
        i = int(np.flatnonzero(episode != ep.index)[0])
        raise SefaInputError(f"row {i} of episode {ep.index} has episode_index {episode[i]}: "
                             f"the episodes table gives episode {ep.index} {ep.length} frames, "
                             "the data file another count", file=file, key="episode_index")
    frame = table.column("frame_index").to_numpy()
    if not np.array_equal(frame, np.arange(ep.length)):
        i = int(np.flatnonzero(frame != np.arange(ep.length))[0])
        raise SefaInputError(f"frame_index {frame[i]} where {i} is expected", file=file,
                             key="frame_index", where=f"episode {ep.index}, frame {i}")


def check_grid(ts: np.ndarray, fps: float, ep: EpisodeRef) -> None:
    """Timestamps must be finite and consecutive ones step by 1/fps within LeRobot's tolerance
    (its own check; a NaN step compares False with any tolerance, so finiteness is checked
    first: a NaN would otherwise take the previous video frame)."""
    bad = ~np.isfinite(ts)
    if bad.any():
        i = int(np.argmax(bad))
        raise SefaInputError(f"timestamp {ts[i]} is not a finite number of seconds: the frame "
                             "cannot be placed on the time grid (nor its video frame found)",
                             file=str(ep.data_file), key="timestamp",
                             where=f"episode {ep.index}, frame {i}")
    step = np.diff(ts)
    off = np.abs(step - 1.0 / fps)
    if len(off) and off.max() > TOLERANCE_S:
        i = int(np.argmax(off > TOLERANCE_S))
        raise SefaInputError(
            f"timestamp {ts[i + 1]:.6f} s follows {ts[i]:.6f} s: a step of {step[i] * 1e3:.3f} ms "
            f"where {fps:g} fps needs {1e3 / fps:.3f} ms (off by {(step[i] - 1 / fps) * 1e3:+.3f} "
            f"ms, tolerance {TOLERANCE_S * 1e3:g} ms); refused, as LeRobot's loader refuses it, "
            "rather than resampled: dropped or doubled frames cannot be told from a clock error",
            file=str(ep.data_file), key="timestamp", where=f"episode {ep.index}, frame {i + 1}")


def _lowdim_and_images(table, ep: EpisodeRef, layout: Layout, keys: list[str],
                       allow_lossy_cast: bool = False) -> tuple[dict, np.ndarray]:
    ts = _timestamps(table)
    check_grid(ts, layout.fps, ep)
    data: dict[str, np.ndarray] = {}
    for k in keys:
        f = layout.features[k]
        if f["dtype"] == "video":
            continue
        if k not in table.column_names:
            raise SefaInputError("column missing from the data file", file=str(ep.data_file), key=k)
        column = table.column(k)
        if f["dtype"] == "image":
            data[k] = _images(column, ep, k)
            check_image_size(data[k], f, str(ep.data_file), k, ep)
        else:
            data[k] = column_array(column, f, str(ep.data_file), k, allow_lossy_cast,
                                   check=lambda raw, k=k: check_statistics(k, raw, ep))
    return data, ts


def column_array(column, feature: dict, file: str, key: str, allow_lossy_cast: bool = False,
                 check: Callable[[np.ndarray], None] | None = None) -> np.ndarray:
    """A (nested) list column as an array (rows, *shape) of the feature's dtype; a dtype that
    would change a value is refused unless `allow_lossy_cast` (as pyarrow's safe cast, which
    LeRobot's loader applies: 3.0 may become an int, 3.5 or 233.0 as int8 may not). `check`
    sees the values as stored, (rows, values), before any cast."""
    import pyarrow as pa

    arr = column.combine_chunks() if isinstance(column, pa.ChunkedArray) else column
    if arr.null_count:
        raise SefaInputError(f"{arr.null_count} missing (null) values", file=file, key=key)
    rows = len(arr)
    while pa.types.is_list(arr.type) or pa.types.is_fixed_size_list(arr.type) \
            or pa.types.is_large_list(arr.type):
        arr = arr.flatten()
    raw = arr.to_numpy(zero_copy_only=False)
    if raw.dtype.kind not in "biuf":
        raise SefaInputError(f"the column holds {arr.type} values where info.json says "
                             f"{feature['dtype']}", file=file, key=key)
    if check is not None and rows and raw.size % rows == 0:
        check(raw.reshape(rows, -1))
    changed = None if allow_lossy_cast else lossy_cast(raw, np.dtype(feature["dtype"]))
    if changed:
        raise SefaInputError(f"info.json's dtype {feature['dtype']} cannot hold these values: "
                             f"{changed}; ingest with --allow-lossy-cast if that is meant",
                             file=file, key=key)
    with np.errstate(all="ignore"):
        values = raw.astype(feature["dtype"], copy=False)
    shape = tuple(int(s) for s in feature.get("shape") or [1])
    if values.size != rows * int(np.prod(shape)):
        raise SefaInputError(f"{values.size // max(rows, 1)} values per frame where info.json "
                             f"says shape {list(shape)}", file=file, key=key)
    return values.reshape((rows,) + shape)


def check_image_size(frames: np.ndarray, feature: dict, file: str, key: str,
                     ep: EpisodeRef) -> None:
    """Frames must have the height and width info.json gives: (h, w, c) as LeRobot writes it,
    or (c, h, w) as older datasets do. Channels are not compared: sefa reads every image as
    RGB."""
    shape = [int(s) for s in feature.get("shape") or []]
    if len(shape) != 3 or not len(frames):
        return
    h, w = frames.shape[1:3]
    if [h, w] != shape[:2] and [h, w] != shape[1:]:
        raise SefaInputError(f"frames of {h}x{w} (height x width) where info.json's shape is "
                             f"{shape}", file=file, key=key, where=f"episode {ep.index}")


# How far what is read may be from the dataset's own statistics of its episode, relative to the
# feature's magnitude there (max |min|, |max|, at least 1). LeRobot stores the min and max of
# the values themselves (a float32 widened to float64: exact), so they get a tolerance only for
# writers that round what they print (1e-5: six significant digits). Its mean is np.mean over
# the frames in float32 (compute_stats.py), whose rounding grows with the episode's length: on
# the shared Push-T fixtures (206 + 5 episodes of up to 246 frames) the largest gap measured
# is 1.0e-6 of the magnitude (min and max: 0); a sequential float32 sum of n frames is off by
# at most about n * 6e-8, so 1e-3 holds for episodes of more than 10,000 frames. A flipped bit
# that matters is far beyond both (209 read as 4.6e21; an exponent bit at least doubles a value).
STATS_RTOL = {"min": 1e-5, "max": 1e-5, "mean": 1e-3}


def check_statistics(k: str, values: np.ndarray, ep: EpisodeRef) -> None:
    """One feature's values in an episode, (frames, values) as stored, against the min, max
    and mean the dataset recorded for that episode (where it did)."""
    recorded = ep.stats.get(k)
    if recorded is None or not len(values):
        return
    x = values.astype(np.float64)
    ours = {"min": x.min(0), "max": x.max(0), "mean": x.mean(0)}
    try:
        theirs = {s: np.asarray(v, np.float64).reshape(-1) for s, v in recorded.items()}
    except (TypeError, ValueError):
        return  # not numbers: a table sefa does not understand is no check
    if any(v.shape != ours["min"].shape for v in theirs.values()):
        return
    scale = np.maximum(1.0, np.maximum(np.abs(theirs["min"]), np.abs(theirs["max"])))
    for s in ("min", "max", "mean"):
        # a NaN or Inf read is left to the store's own check of non-finite values (with its
        # own line); a recorded NaN checks nothing
        off = np.isfinite(ours[s]) & np.isfinite(theirs[s]) & ~(
            np.abs(ours[s] - theirs[s]) <= STATS_RTOL[s] * scale)
        if off.any():
            j = int(np.argmax(off))
            raise SefaInputError(
                f"value {j} has {s} {ours[s][j]:.9g} as read but {theirs[s][j]:.9g} in the "
                "dataset's own statistics of this episode: the data file is damaged (parquet "
                "has no checksum; a flipped bit reads as a wild value) or the statistics are "
                "stale (--skip-stats-check reads it without them)", file=str(ep.data_file), key=k, where=f"episode {ep.index}")


def _images(column, ep: EpisodeRef, key: str) -> np.ndarray:
    from PIL import Image

    frames = []
    for i, cell in enumerate(column.to_pylist()):
        raw = (cell or {}).get("bytes") if isinstance(cell, dict) else cell
        if not raw:
            raise SefaInputError("no image bytes (an image stored by path only)",
                                 file=str(ep.data_file), key=key, where=f"episode {ep.index}, frame {i}")
        try:
            with Image.open(io.BytesIO(raw)) as im:
                frames.append(np.asarray(im.convert("RGB")))
        except OSError as e:
            raise SefaInputError(f"undecodable image ({e})", file=str(ep.data_file), key=key,
                                 where=f"episode {ep.index}, frame {i}") from None
        if frames[-1].shape != frames[0].shape:
            raise SefaInputError(f"an image of {frames[-1].shape[0]}x{frames[-1].shape[1]} "
                                 f"where the episode's first is {frames[0].shape[0]}x"
                                 f"{frames[0].shape[1]} (height x width)", file=str(ep.data_file),
                                 key=key, where=f"episode {ep.index}, frame {i}")
    return np.stack(frames)


class _VideoStream:
    """Frames of one video file decoded in order; an episode takes the frames at its times.

    Episodes of a v3.0 file follow each other, so one pass decodes the file once; an episode
    that starts before the stream's position (a file listed out of order) seeks back."""

    def __init__(self, file: Path, key: str):
        import av

        if not file.is_file():
            raise SefaInputError("missing video file (the episodes table points to it)",
                                 file=str(file), key=key)
        self.file, self.key = file, key
        try:
            self.container = av.open(str(file))
            self.stream = self.container.streams.video[0]
        except (av.FFmpegError, IndexError) as e:
            if is_lfs_pointer(file):
                raise lfs_error([file], file.parent) from None
            raise SefaInputError(f"not a readable video ({clip(str(e))})", file=str(file),
                                 key=key) from None
        self.stream.thread_type = "AUTO"
        self._frames = self._decode()
        self.current: tuple[float, object] | None = None

    def _decode(self) -> Iterator[tuple[float, object]]:
        import av

        try:
            for frame in self.container.decode(self.stream):
                if frame.pts is None:
                    raise SefaInputError("a video frame without a timestamp (pts): LeRobot "
                                         "fetches frames by timestamp", file=str(self.file),
                                         key=self.key)
                yield float(frame.pts * self.stream.time_base), frame
        except av.FFmpegError as e:
            raise SefaInputError(f"video decoding failed ({e})", file=str(self.file),
                                 key=self.key) from None

    def _seek(self, t: float) -> None:
        self.container.seek(int(t / self.stream.time_base), stream=self.stream, backward=True)
        self._frames = self._decode()
        self.current = None

    def frames(self, times: np.ndarray, ep: EpisodeRef) -> np.ndarray:
        if self.current is not None and times[0] < self.current[0] - TOLERANCE_S:
            self._seek(float(times[0]))
        out = []
        for i, t in enumerate(times):
            while self.current is None or self.current[0] < t - TOLERANCE_S:
                nxt = next(self._frames, None)
                if nxt is None:
                    last = "no frame" if self.current is None else f"its last frame at {self.current[0]:.4f} s"
                    raise SefaInputError(
                        f"the video is shorter than its episode: frame {i} needs time {t:.4f} s, "
                        f"the file has {last}", file=str(self.file), key=self.key,
                        where=f"episode {ep.index}, frame {i}")
                self.current = nxt
            if abs(self.current[0] - t) > TOLERANCE_S:
                raise SefaInputError(
                    f"no video frame within {TOLERANCE_S:g} s of {t:.4f} s (the nearest is at "
                    f"{self.current[0]:.4f} s)", file=str(self.file), key=self.key,
                    where=f"episode {ep.index}, frame {i}")
            out.append(self.current[1].to_ndarray(format="rgb24"))
        return np.stack(out)

    def close(self) -> None:
        self.container.close()


STAT_NAMES = ("min", "max", "mean", "std", "q01", "q99")


def dataset_stats(layout: Layout) -> tuple[dict[str, dict[str, list]], str | None]:
    """The dataset's own statistics of its numeric features, as `sefa inspect` shows them:
    meta/stats.json (LeRobot's aggregate: min, max, mean, std and quantiles), else the
    episodes' statistics combined (min of the minima, max of the maxima, the mean weighted by
    episode length); where they came from, or None when the dataset has neither."""
    import json

    numeric = {k for k, f in layout.features.items() if f.get("dtype") not in ("video", "image")}
    try:
        recorded = json.loads((layout.root / "meta" / "stats.json").read_text())
    except (OSError, ValueError):
        recorded = None
    if isinstance(recorded, dict):
        out = {k: {s: v[s] for s in STAT_NAMES if isinstance(v.get(s), list)}
               for k, v in recorded.items() if k in numeric and isinstance(v, dict)}
        return {k: v for k, v in out.items() if "mean" in v}, "meta/stats.json"
    per_key: dict[str, list] = {}
    for e in layout.episodes:
        for k, st in e.stats.items():
            per_key.setdefault(k, []).append((e.length, st))
    out = {}
    for k, rows in per_key.items():
        w = np.array([n for n, _ in rows], np.float64)
        mean = (np.array([st["mean"] for _, st in rows], np.float64) * w[:, None]).sum(0) / w.sum()
        out[k] = {"min": np.min([st["min"] for _, st in rows], axis=0).tolist(),
                  "max": np.max([st["max"] for _, st in rows], axis=0).tolist(),
                  "mean": mean.tolist()}
    return out, ("the episodes' statistics" if out else None)


def inspect_lerobot(path: str | Path) -> dict:
    """What a LeRobot dataset holds (its tables; no frame is decoded), and whether ingest can
    read it: a feature whose files are missing or not fetched (Git LFS pointers), or a camera
    the episodes table does not place, is "not read", with why; `problem` is then the line
    ingest would stop on (None when it would read every readable feature)."""
    layout = load_layout(path)
    lengths = [e.length for e in layout.episodes]
    keys, skipped = _readable(layout.features)
    for k in keys:
        if k in layout.unplaced:
            skipped[k] = layout.unplaced_error(k, []).what
    cameras = [k for k in keys if layout.features[k]["dtype"] == "video" and k not in skipped]
    check = referenced_files(layout, cameras)
    problem = check.error(layout.root)
    broken = {p: "missing" for p in check.missing} | {p: "Git LFS pointers, not fetched"
                                                       for p in check.pointers}
    for p, why in broken.items():
        if check.keys[p] is None:  # a data file: no feature can be read
            skipped |= {k: f"data files {why}" for k in keys if k not in skipped}
        else:
            skipped[check.keys[p]] = f"video files {why}"
    if problem is None:
        others = [o for o in keys if o not in layout.unplaced]
        problem = next((layout.unplaced_error(k, others) for k in keys if k in layout.unplaced),
                       None)
    stats, source = dataset_stats(layout)
    return {
        "path": str(path), "format": "lerobot", "codebase_version": layout.version,
        "fps": layout.fps, "robot_type": layout.info.get("robot_type"),
        "n_episodes": len(lengths), "n_frames": sum(lengths),
        "episode_length": {"min": min(lengths), "max": max(lengths),
                           "mean": sum(lengths) / len(lengths)} if lengths else {},
        "features": {k: {"dtype": f.get("dtype"), "shape": f.get("shape"),
                         "codec": (f.get("info") or {}).get("video.codec"),
                         "read": k not in skipped, "stats": stats.get(k)}
                     for k, f in layout.features.items()},
        "stats_source": source,
        "skipped": skipped,
        "tasks": layout.tasks,
        "data_files": sorted({str(e.data_file.relative_to(layout.root)) for e in layout.episodes}),
        "files": {"referenced": len(check.episode), "missing": [str(p) for p in check.missing],
                  "lfs_pointers": [str(p) for p in check.pointers]},
        "problem": problem.line() if problem is not None else None,
    }
