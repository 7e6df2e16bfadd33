"""A local LeRobot dataset's tables (v3.0 and v2.1): info.json, tasks and the episodes table.

v3.0 (LeRobot 0.4 and later) packs many episodes per data parquet and per video file; its
episodes table (``meta/episodes/*/*.parquet``) says where each episode's rows and video span
are. v2.1 has one parquet and one video per episode, found through info.json's ``data_path``
and ``video_path`` templates, and JSON-lines tables (``meta/episodes.jsonl``,
``meta/tasks.jsonl``). Both become one list of `EpisodeRef`, so the reader does not care which
version it reads. Only the tables are read here; frames are read by `lerobot_reader`.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

from sefa_data.errors import SefaInputError
from sefa_data.validate import check_fps

VERSIONS = ("v2.1", "v3.0")
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


@dataclass
class Layout:
    root: Path
    info: dict
    version: str
    fps: float
    features: dict[str, dict]  # the dataset's own features (LeRobot's default columns left out)
    tasks: list[str]  # by task_index
    episodes: list[EpisodeRef]


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
    version = info.get("codebase_version")
    if version not in VERSIONS:
        raise SefaInputError(f"codebase_version {version!r} is not one sefa reads (it reads "
                             f"{' and '.join(VERSIONS)})", file=str(root / "meta" / "info.json"),
                             key="codebase_version")
    fps = check_fps(info.get("fps"), file=str(root / "meta" / "info.json"))
    features = {k: v for k, v in info.get("features", {}).items() if k not in DEFAULT_COLUMNS}
    if version == "v3.0":
        tasks, episodes = _tasks_v30(root), _episodes_v30(root, info, features)
    else:
        tasks, episodes = _tasks_v21(root), _episodes_v21(root, info, features)
    layout = Layout(root, info, version, fps, features, tasks, episodes)
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


def read_parquet(path: Path, columns: list[str] | None = None):
    """A whole (small) parquet table; a damaged or truncated file is one line naming it."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    if not path.is_file():
        raise SefaInputError("missing", file=str(path))
    try:
        return pq.read_table(path, columns=columns)
    except (pa.ArrowException, OSError, ValueError) as e:
        raise SefaInputError(f"unreadable parquet ({' '.join(str(e).split())[:160]}): truncated "
                             "or damaged", file=str(path)) from None


def _tasks_v30(root: Path) -> list[str]:
    table = read_parquet(root / "meta" / "tasks.parquet").to_pydict()
    if "task_index" not in table or "task" not in table:
        # LeRobot writes the task string as the pandas index, which pyarrow reads as a column
        raise SefaInputError("no task_index and task columns", file=str(root / "meta" / "tasks.parquet"))
    return _by_index(table["task_index"], table["task"], root / "meta" / "tasks.parquet")


def _tasks_v21(root: Path) -> list[str]:
    rows = _jsonl(root / "meta" / "tasks.jsonl")
    return _by_index([r.get("task_index") for r in rows], [r.get("task") for r in rows],
                     root / "meta" / "tasks.jsonl")


def _by_index(indices: list, values: list, file: Path) -> list[str]:
    if sorted(indices) != list(range(len(indices))):
        raise SefaInputError(f"task_index values {sorted(indices)[:8]} are not 0..{len(indices) - 1}",
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
                rows.append(json.loads(line))
            except ValueError as e:
                raise SefaInputError(f"not valid JSON ({e})", file=str(path), where=f"line {n}") from None
    return rows


def _video_keys(features: dict) -> list[str]:
    return [k for k, f in features.items() if f.get("dtype") == "video"]


def _episodes_v30(root: Path, info: dict, features: dict) -> list[EpisodeRef]:
    files = sorted((root / "meta" / "episodes").glob("chunk-*/file-*.parquet"))
    if not files:
        raise SefaInputError("no episodes table (meta/episodes/chunk-*/file-*.parquet)", file=str(root))
    data_tpl = info.get("data_path", "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet")
    video_tpl = info.get("video_path",
                         "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4")
    out = []
    for file in files:
        rows = read_parquet(file).to_pylist()
        for r in rows:
            try:
                data = root / data_tpl.format(chunk_index=r["data/chunk_index"],
                                              file_index=r["data/file_index"])
                videos = {k: (root / video_tpl.format(
                    video_key=k, chunk_index=r[f"videos/{k}/chunk_index"],
                    file_index=r[f"videos/{k}/file_index"]),
                    float(r[f"videos/{k}/from_timestamp"])) for k in _video_keys(features)}
                out.append(EpisodeRef(int(r["episode_index"]), int(r["length"]),
                                      list(r.get("tasks") or []), data,
                                      int(r["dataset_from_index"]), videos))
            except KeyError as e:
                raise SefaInputError(f"no column {e.args[0]}", file=str(file)) from None
    # rows of a file are numbered from its first episode's dataset_from_index
    first = {}
    for e in out:
        first[e.data_file] = min(first.get(e.data_file, e.start), e.start)
    for e in out:
        e.start -= first[e.data_file]
    return _ordered(out, files[0].parent.parent)


def _episodes_v21(root: Path, info: dict, features: dict) -> list[EpisodeRef]:
    rows = _jsonl(root / "meta" / "episodes.jsonl")
    chunks = int(info.get("chunks_size", 1000))
    data_tpl = info.get("data_path")
    video_tpl = info.get("video_path")
    if not data_tpl or (_video_keys(features) and not video_tpl):
        raise SefaInputError("no data_path or video_path template", file=str(root / "meta" / "info.json"))
    out = []
    for n, r in enumerate(rows, start=1):
        if "episode_index" not in r or "length" not in r:
            raise SefaInputError("a row without episode_index or length",
                                 file=str(root / "meta" / "episodes.jsonl"), where=f"line {n}")
        i = int(r["episode_index"])
        fmt = {"episode_chunk": i // chunks, "episode_index": i}
        videos = {k: (root / video_tpl.format(video_key=k, **fmt), 0.0) for k in _video_keys(features)}
        out.append(EpisodeRef(i, int(r["length"]), list(r.get("tasks") or []),
                              root / data_tpl.format(**fmt), 0, videos))
    return _ordered(out, root / "meta" / "episodes.jsonl")


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
    if "total_frames" in info and int(info["total_frames"]) != frames:
        raise SefaInputError(f"total_frames {info['total_frames']} but the episodes table sums "
                             f"to {frames} frames", file=file, key="total_frames")
    if "total_episodes" in info and int(info["total_episodes"]) != len(layout.episodes):
        raise SefaInputError(f"total_episodes {info['total_episodes']} but the episodes table "
                             f"lists {len(layout.episodes)}", file=file, key="total_episodes")
