"""A local LeRobot dataset's tables (v3.0 and v2.1): info.json, tasks and the episodes table.

v3.0 (LeRobot 0.4 and later) packs many episodes per data parquet and per video file; its
episodes table (``meta/episodes/*/*.parquet``) says where each episode's rows and video span
are. v2.1 has one parquet and one video per episode, found through info.json's ``data_path``
and ``video_path`` templates, and JSON-lines tables (``meta/episodes.jsonl``,
``meta/tasks.jsonl``, ``meta/episodes_stats.jsonl``). v2.0 is v2.1 without the per-episode
statistics (LeRobot's own v2.0 -> v2.1 conversion only computes them), so it is read as v2.1.
All become one list of `EpisodeRef`, so the reader does not care which version it reads. Only
the tables are read here; frames are read by `lerobot.reader`.

info.json is read like a topic map: every value sefa uses is type-checked here, so that a
malformed one is one line naming the file and the key, never an exception from deep inside.
"""

from __future__ import annotations

import json
import math
import string
from dataclasses import dataclass, field
from pathlib import Path

from sefa_data.errors import SefaInputError, clip
from sefa_data.lerobot.files import FileCheck, is_lfs_pointer, parquet_error, read_parquet
from sefa_data.validate import check_fps

VERSIONS = ("v2.0", "v2.1", "v3.0")
# The columns LeRobot adds to every dataset: they are rebuilt from the episode layout, so they
# are checked and not stored.
DEFAULT_COLUMNS = ("timestamp", "frame_index", "episode_index", "index", "task_index")


@dataclass
class EpisodeRef:
    """Where one episode's rows and video frames are."""

    index: int  # episode_index
    length: int  # frames, by the episodes table
    tasks: list[str]
    data_file: Path
    start: int  # its first row in data_file
    videos: dict[str, tuple[Path, float]] = field(default_factory=dict)  # key -> file, start s
    # the dataset's own statistics of this episode, where it has them: feature -> {"min": [...],
    # "max": [...], "mean": [...]} (v3.0: the episodes table's stats/* columns; v2.1:
    # meta/episodes_stats.jsonl)
    stats: dict[str, dict[str, list]] = field(default_factory=dict)
    table: Path | None = None  # the episodes table this row came from


@dataclass
class Layout:
    root: Path
    info: dict
    version: str
    fps: float
    features: dict[str, dict]  # the dataset's own features (LeRobot's default columns left out)
    tasks: list[str]  # by task_index
    episodes: list[EpisodeRef]
    # a camera whose episodes cannot be placed in its videos (an episodes table without its
    # videos/KEY/* columns): key -> (that table, the columns it lacks); refused only when the
    # camera is read (`unplaced_error`), so that --key can leave it out
    unplaced: dict[str, tuple[Path, list[str]]] = field(default_factory=dict)

    def unplaced_error(self, key: str, others: list[str]) -> SefaInputError:
        table, absent = self.unplaced[key]
        read = " ".join(f"--key {k}" for k in others)
        return SefaInputError(
            f"the episodes table has no column {', '.join(absent)}: where each episode's frames "
            f"are in this camera's video is not known, so it cannot be read"
            + (f"; leave it out with --key ({read})" if others else ""),
            file=str(table), key=key)


def is_lerobot(path: Path) -> bool:
    """A folder with meta/info.json, or with meta/ and data/ (then info.json is reported missing)."""
    path = Path(path)
    if not path.is_dir() or (path / ".zgroup").exists() or (path / "zarr.json").exists():
        return False  # a Zarr store has meta/ and data/ too
    return (path / "meta" / "info.json").is_file() or ((path / "meta").is_dir()
                                                        and (path / "data").is_dir())


def load_layout(root: str | Path) -> Layout:
    root = Path(root)
    info = _info(root)
    file = str(root / "meta" / "info.json")
    version = info.get("codebase_version")
    if version not in VERSIONS:
        raise SefaInputError(f"codebase_version {version!r} is not one sefa reads (it reads "
                             f"{', '.join(VERSIONS)}; convert older datasets with LeRobot's "
                             "own conversion scripts, lerobot.datasets.v21 and v30)",
                             file=file, key="codebase_version")
    fps = check_fps(info.get("fps"), file=file)
    _check_features(info["features"], file)
    features = {k: v for k, v in info["features"].items() if k not in DEFAULT_COLUMNS}
    unplaced: dict[str, tuple[Path, list[str]]] = {}
    if version == "v3.0":
        tasks, episodes = _tasks_v30(root), _episodes_v30(root, info, features, unplaced)
    else:
        tasks, episodes = _tasks_v21(root), _episodes_v21(root, info, features)
    layout = Layout(root, info, version, fps, features, tasks, episodes, unplaced)
    _check_totals(layout)
    return layout


def _info(root: Path) -> dict:
    path = root / "meta" / "info.json"
    if not path.is_file():
        raise SefaInputError("no meta/info.json: not a LeRobot dataset folder (or an incomplete "
                             "one)", file=str(root))
    try:
        info = json.loads(path.read_text())
    except (ValueError, UnicodeDecodeError) as e:
        raise SefaInputError(f"not valid JSON ({e})", file=str(path)) from None
    if not isinstance(info, dict) or not isinstance(info.get("features"), dict):
        raise SefaInputError("no features table", file=str(path), key="features")
    return info


def whole(value: object, *, file: str, key: str, minimum: int = 0,
          where: str | None = None) -> int:
    """`value` as an int when it is a whole number >= minimum (JSON may write 161.0)."""
    if isinstance(value, float) and math.isfinite(value) and value.is_integer():
        value = int(value)
    if isinstance(value, bool) or not isinstance(value, int) and not (
            hasattr(value, "dtype") and getattr(value, "dtype").kind in "iu"):
        raise SefaInputError(f"must be a whole number, got {value!r}", file=file, key=key,
                             where=where)
    if int(value) < minimum:
        raise SefaInputError(f"must be at least {minimum}, got {value!r}", file=file, key=key,
                             where=where)
    return int(value)


def _check_features(features: dict, file: str) -> None:
    """Each feature a mapping with a dtype and a shape of whole numbers (an image or video:
    three of them); what sefa reads of a feature is checked, its other keys are LeRobot's."""
    for k, f in features.items():
        key = f"features.{k}"
        if not isinstance(f, dict):
            raise SefaInputError(clip(f"must be a mapping with dtype and shape, got {f!r}", 200),
                                 file=file, key=key)
        if not isinstance(f.get("dtype"), str):
            raise SefaInputError(f"must be a dtype name (float32, video, ...), got "
                                 f"{f.get('dtype')!r}", file=file, key=f"{key}.dtype")
        shape = f.get("shape")
        if shape is None:
            continue  # one value per frame, as LeRobot's scalar columns
        if not isinstance(shape, list) or not shape:
            raise SefaInputError(f"must be a list of whole numbers, got {shape!r}", file=file,
                                 key=f"{key}.shape")
        for s in shape:
            whole(s, file=file, key=f"{key}.shape", minimum=1)
        if f["dtype"] in ("image", "video") and len(shape) != 3:
            raise SefaInputError(f"an {f['dtype']} feature has a shape of three numbers "
                                 f"(height, width, channels), got {shape!r}", file=file,
                                 key=f"{key}.shape")


def _tasks_v30(root: Path) -> list[str]:
    """The task strings by task_index. LeRobot reads this table with pandas and takes the task
    string from its index (`tasks.iloc[task_index].name`): a table that pandas wrote from a
    DataFrame indexed by task holds the strings in the index column its metadata names
    (`__index_level_0__` when the index is unnamed, else the index's name), and maybe no
    `task` column at all."""
    path = root / "meta" / "tasks.parquet"
    table = read_parquet(path)
    columns = table.to_pydict()
    strings = next((c for c in _pandas_index_columns(table) if c in columns
                    and all(isinstance(v, str) for v in columns[c])), None)
    strings = strings or ("task" if "task" in columns else None)
    if strings is None:
        raise SefaInputError(f"no task strings: neither a pandas index of strings nor a task "
                             f"column (columns: {', '.join(columns)})", file=str(path))
    # LeRobot looks a task up by its row (iloc); its writer numbers the rows in task_index
    indices = columns.get("task_index", list(range(table.num_rows)))
    return _by_index(indices, columns[strings], path)


def _pandas_index_columns(table) -> list[str]:
    """The columns pandas stored its index in (named in the schema's pandas metadata)."""
    meta = (table.schema.metadata or {}).get(b"pandas")
    try:
        names = json.loads(meta)["index_columns"] if meta else []
    except (ValueError, KeyError, TypeError):
        return []
    # a RangeIndex is stored as a description, not a column
    return [n for n in names if isinstance(n, str)]


def _tasks_v21(root: Path) -> list[str]:
    rows = _jsonl(root / "meta" / "tasks.jsonl")
    return _by_index([r.get("task_index") for r in rows], [r.get("task") for r in rows],
                     root / "meta" / "tasks.jsonl")


def _by_index(indices: list, values: list, file: Path) -> list[str]:
    if not all(isinstance(i, int) and not isinstance(i, bool) for i in indices) \
            or sorted(indices) != list(range(len(indices))):
        raise SefaInputError(f"task_index values {indices[:8]} are not 0..{len(indices) - 1}",
                             file=str(file), key="task_index")
    out = [""] * len(indices)
    for i, v in zip(indices, values):
        out[i] = str(v)
    return out


def _jsonl(path: Path) -> list[dict]:
    if not path.is_file():
        raise SefaInputError("missing", file=str(path))
    rows = []
    for n, line in enumerate(path.read_text().splitlines(), start=1):
        if line.strip():
            try:
                row = json.loads(line)
            except ValueError as e:
                raise SefaInputError(f"not valid JSON ({e})", file=str(path), where=f"line {n}") from None
            if not isinstance(row, dict):
                raise SefaInputError(f"a line that is not a JSON object: {line[:80]!r}",
                                     file=str(path), where=f"line {n}")
            rows.append(row)
    return rows


def _video_keys(features: dict) -> list[str]:
    return [k for k, f in features.items() if f.get("dtype") == "video"]


# The fields LeRobot fills its path templates with: v3.0 (chunk_index, file_index, video_key)
# and v2.1 (episode_chunk, episode_index, video_key). Community writers mix the two sets, so a
# v2.1 template may use either; in v2.1 every episode is its own file, numbered by episode.
_V30_FIELDS = ("chunk_index", "file_index", "video_key")
_V21_FIELDS = ("episode_chunk", "chunk_index", "episode_index", "file_index", "video_key")


def _template(info: dict, key: str, file: str, fields: tuple[str, ...],
              default: str | None = None) -> str:
    """info.json's path template `key`, checked: a string whose every field is one LeRobot
    fills and that formats (a malformed one is one line here, not at its first use)."""
    tpl = info.get(key, default)
    if not isinstance(tpl, str) or not tpl:
        raise SefaInputError(f"must be a path template string, got {tpl!r}", file=file, key=key)
    try:
        named = [f for _, f, _, _ in string.Formatter().parse(tpl) if f is not None]
    except ValueError as e:
        raise SefaInputError(f"malformed path template {tpl!r} ({e})", file=file, key=key) from None
    for f in named:
        base = f.split(".")[0].split("[")[0]
        if base not in fields:
            raise SefaInputError(f"path template {tpl!r} uses {{{f}}}, not a field LeRobot fills "
                                 f"(it fills {', '.join(fields)})", file=file, key=key)
    fill(tpl, {f: ("k" if f == "video_key" else 0) for f in fields}, file, key)
    return tpl


def fill(tpl: str, values: dict, file: str, key: str) -> str:
    try:
        return tpl.format(**values)
    except (ValueError, KeyError, IndexError, AttributeError, TypeError) as e:
        raise SefaInputError(f"malformed path template {tpl!r} ({type(e).__name__}: {e})",
                             file=file, key=key) from None


def _stats_of(row: dict, keys: list[str], prefix: str = "stats/") -> dict[str, dict[str, list]]:
    """min, max and mean per feature from an episodes-table row, where present and numeric."""
    out = {}
    for k in keys:
        got = {}
        for s in ("min", "max", "mean"):
            v = row.get(f"{prefix}{k}/{s}")
            if isinstance(v, (int, float)) and not isinstance(v, bool):
                v = [v]
            if isinstance(v, list):
                got[s] = v
        if len(got) == 3:
            out[k] = got
    return out


# the columns of the episodes table that place an episode in a camera's video
VIDEO_COLUMNS = ("chunk_index", "file_index", "from_timestamp")


def _episodes_v30(root: Path, info: dict, features: dict,
                  unplaced: dict[str, tuple[Path, list[str]]]) -> list[EpisodeRef]:
    """The episodes of every episodes table; a camera whose columns a table lacks goes to
    `unplaced` (with the columns it lacks), so that --key can leave it out."""
    files = sorted((root / "meta" / "episodes").glob("chunk-*/file-*.parquet"))
    if not files:
        raise SefaInputError("no episodes table (meta/episodes/chunk-*/file-*.parquet)", file=str(root))
    info_file = str(root / "meta" / "info.json")
    data_tpl = _template(info, "data_path", info_file, _V30_FIELDS,
                         "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet")
    video_keys = _video_keys(features)
    video_tpl = _template(info, "video_path", info_file, _V30_FIELDS,
                          "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4") \
        if video_keys else None
    lowdim = [k for k, f in features.items() if f["dtype"] not in ("image", "video")]
    out = []
    for file in files:
        table = read_parquet(file)
        for k in video_keys:
            absent = [f"videos/{k}/{c}" for c in VIDEO_COLUMNS
                      if f"videos/{k}/{c}" not in table.column_names]
            if absent:
                unplaced.setdefault(k, (file, absent))
        placed = [k for k in video_keys if k not in unplaced]
        for n, r in enumerate(table.to_pylist()):
            out.append(_episode_v30(r, root, file, n, data_tpl, video_tpl, placed, lowdim,
                                    info_file))
    # rows of a file are numbered from its first episode's dataset_from_index
    first = {}
    for e in out:
        first[e.data_file] = min(first.get(e.data_file, e.start), e.start)
    for e in out:
        e.start -= first[e.data_file]
    return _ordered(out, files[0].parent.parent)


def _episode_v30(r: dict, root: Path, file: Path, n: int, data_tpl: str, video_tpl: str | None,
                 video_keys: list[str], lowdim: list[str], info_file: str) -> EpisodeRef:
    def number(col: str, minimum: int = 0) -> int:
        if col not in r:
            raise SefaInputError(f"no column {col}", file=str(file))
        return whole(r[col], file=str(file), key=col, minimum=minimum, where=f"row {n}")

    index = number("episode_index")
    data = root / fill(data_tpl, {"chunk_index": number("data/chunk_index"),
                                  "file_index": number("data/file_index"), "video_key": ""},
                       info_file, "data_path")
    videos = {}
    for k in video_keys:
        start = r[f"videos/{k}/from_timestamp"]
        if isinstance(start, bool) or not isinstance(start, (int, float)) \
                or not math.isfinite(start) or start < 0:
            raise SefaInputError(f"must be a time in seconds >= 0, got {start!r}", file=str(file),
                                 key=f"videos/{k}/from_timestamp", where=f"row {n}")
        path = fill(video_tpl, {"video_key": k, "chunk_index": number(f"videos/{k}/chunk_index"),
                                "file_index": number(f"videos/{k}/file_index")},
                    info_file, "video_path")
        videos[k] = (root / path, float(start))
    tasks = r.get("tasks") or []
    if not isinstance(tasks, list) or not all(isinstance(t, str) for t in tasks):
        raise SefaInputError(clip(f"must be a list of task strings, got {tasks!r}", 200),
                             file=str(file), key="tasks", where=f"row {n}")
    return EpisodeRef(index, number("length"), tasks, data, number("dataset_from_index"), videos,
                      _stats_of(r, lowdim), file)


def _episodes_v21(root: Path, info: dict, features: dict) -> list[EpisodeRef]:
    table = root / "meta" / "episodes.jsonl"
    rows = _jsonl(table)
    info_file = str(root / "meta" / "info.json")
    chunks = whole(info.get("chunks_size", 1000), file=info_file, key="chunks_size", minimum=1)
    data_tpl = _template(info, "data_path", info_file, _V21_FIELDS)
    video_keys = _video_keys(features)
    video_tpl = _template(info, "video_path", info_file, _V21_FIELDS) if video_keys else None
    lowdim = [k for k, f in features.items() if f["dtype"] not in ("image", "video")]
    stats = _episode_stats_v21(root / "meta" / "episodes_stats.jsonl", lowdim)
    out = []
    for n, r in enumerate(rows, start=1):
        where = f"line {n}"
        for col in ("episode_index", "length"):
            if col not in r:
                raise SefaInputError("a row without episode_index or length", file=str(table),
                                     where=where)
        i = whole(r["episode_index"], file=str(table), key="episode_index", where=where)
        length = whole(r["length"], file=str(table), key="length", where=where)
        tasks = r.get("tasks") or []
        if not isinstance(tasks, list) or not all(isinstance(t, str) for t in tasks):
            raise SefaInputError(clip(f"must be a list of task strings, got {tasks!r}", 200),
                                 file=str(table), key="tasks", where=where)
        fmt = {"episode_chunk": i // chunks, "chunk_index": i // chunks, "episode_index": i,
               "file_index": i}
        videos = {k: (root / fill(video_tpl, {**fmt, "video_key": k}, info_file, "video_path"),
                      0.0) for k in video_keys}
        out.append(EpisodeRef(i, length, tasks,
                              root / fill(data_tpl, {**fmt, "video_key": ""}, info_file,
                                          "data_path"),
                              0, videos, stats.get(i, {}), table))
    return _ordered(out, table)


def _episode_stats_v21(path: Path, keys: list[str]) -> dict[int, dict]:
    """meta/episodes_stats.jsonl (v2.1; v2.0 has none): episode_index -> feature statistics.
    Rows that are not shaped as LeRobot writes them are left out: they are only a check."""
    if not path.is_file():
        return {}
    out = {}
    for r in _jsonl(path):
        i, stats = r.get("episode_index"), r.get("stats")
        if isinstance(i, int) and isinstance(stats, dict):
            flat = {f"{k}/{s}": v for k, d in stats.items() if isinstance(d, dict)
                    for s, v in d.items()}
            out[i] = _stats_of(flat, keys, prefix="")
    return out


def _ordered(episodes: list[EpisodeRef], file: Path) -> list[EpisodeRef]:
    episodes.sort(key=lambda e: e.index)
    seen = [e.index for e in episodes]
    if len(set(seen)) != len(seen):
        dup = next(i for i in seen if seen.count(i) > 1)
        raise SefaInputError(f"episode_index {dup} listed twice", file=str(file))
    bad = next((e for e in episodes if e.length <= 0), None)
    if bad is not None:
        raise SefaInputError(f"length {bad.length}", file=str(file), where=f"episode {bad.index}")
    return episodes


def _check_totals(layout: Layout) -> None:
    info, file = layout.info, str(layout.root / "meta" / "info.json")
    frames = sum(e.length for e in layout.episodes)
    if "total_frames" in info and whole(info["total_frames"], file=file,
                                        key="total_frames") != frames:
        raise SefaInputError(f"total_frames {info['total_frames']} but the episodes table sums "
                             f"to {frames} frames", file=file, key="total_frames")
    if "total_episodes" in info and whole(info["total_episodes"], file=file,
                                          key="total_episodes") != len(layout.episodes):
        raise SefaInputError(f"total_episodes {info['total_episodes']} but the episodes table "
                             f"lists {len(layout.episodes)}", file=file, key="total_episodes")


def referenced_files(layout: Layout, video_keys: list[str]) -> FileCheck:
    """Every data and video file the episodes need for `video_keys`, each looked at once:
    there, and not a Git LFS pointer (nothing is read beyond a pointer's first line)."""
    check = FileCheck()
    for e in layout.episodes:
        for path, key in [(e.data_file, None)] + [(e.videos[k][0], k) for k in video_keys
                                                  if k in e.videos]:
            if path in check.episode:
                continue
            check.episode[path], check.keys[path] = e.index, key
            if not path.is_file():
                check.missing.append(path)
            elif is_lfs_pointer(path):
                check.pointers.append(path)
    return check


def check_referenced_files(layout: Layout, video_keys: list[str]) -> None:
    """Every file the episodes reference, before any frame is decoded: each data parquet and
    each video of `video_keys` present and fetched (all that are not said in one line), each
    data parquet readable (its footer) and, in v3.0, holding each of its episodes' rows where
    the episodes table says (its episode_index column alone is read). Published datasets often
    lack some videos: better one line now than after decoding every earlier episode."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    error = referenced_files(layout, video_keys).error(layout.root)
    if error is not None:
        raise error
    by_file: dict[Path, list[EpisodeRef]] = {}
    for e in layout.episodes:
        by_file.setdefault(e.data_file, []).append(e)
    runs: dict[Path, dict[int, tuple[int, int]]] = {}
    for path in by_file:
        try:
            parquet = pq.ParquetFile(path)
            if layout.version == "v3.0" and "episode_index" in parquet.schema_arrow.names:
                column = parquet.read(columns=["episode_index"]).column(0)
                runs[path] = _runs(column.to_numpy())
        except (pa.ArrowException, OSError) as e:
            raise parquet_error(path, e, layout.root) from None
    for e in layout.episodes:
        if e.data_file not in runs or runs[e.data_file].get(e.index, (None,))[0] == e.start:
            continue
        holder = next((p for p, r in runs.items() if e.index in r), None)
        there = (f"its rows are in {holder.relative_to(layout.root)}" if holder is not None
                 else "no data file holds its rows")
        raise SefaInputError(
            f"episode {e.index} points to {e.data_file.relative_to(layout.root)} (row {e.start}),"
            f" but {there}: its data/chunk_index or data/file_index is wrong",
            file=str(e.table), key="data/file_index", where=f"episode {e.index}")


def _runs(episode_index) -> dict[int, tuple[int, int]]:
    """episode -> (first row, rows) of each run of one episode_index value in a file."""
    import numpy as np

    values = np.asarray(episode_index)
    if not len(values):
        return {}
    starts = np.r_[0, np.flatnonzero(np.diff(values)) + 1]
    ends = np.r_[starts[1:], len(values)]
    return {int(values[s]): (int(s), int(t - s)) for s, t in zip(starts, ends)}
