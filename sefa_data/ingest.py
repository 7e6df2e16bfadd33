"""`sefa ingest`: recordings in, episodes appended to a store, one input file at a time.

Each input is one transaction: it lands whole or not at all. With `skip_failed`, a bad input is
reported and the next one is tried; without it, the first bad input stops the run (the inputs
before it stay committed, since each is complete on its own).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Literal

from sefa_data.config_io import to_dict
from sefa_data.episode import Recording
from sefa_data.errors import SefaInputError
from sefa_data.hdf5_reader import Hdf5Options, read_hdf5
from sefa_data.time_align import align_streams
from sefa_data.topic_map import TopicMap, load_topic_map
from sefa_data.zarr_store import EpisodeStore, file_fingerprint

Format = Literal["zarr", "hdf5", "ros"]


@dataclass
class IngestOptions:
    fps: float | None = None  # required for a new store from formats without a clock (Zarr)
    topic_map: str | None = None  # YAML file; required for ROS bags and MCAP
    renames: dict[str, str] = field(default_factory=dict)  # Zarr import: source key -> our key
    keys: list[str] | None = None  # Zarr import: only these source keys (default: all)
    hdf5: Hdf5Options = field(default_factory=Hdf5Options)
    zarr_format: int = 2
    skip_failed: bool = False
    dry_run: bool = False


@dataclass
class InputReport:
    path: str
    status: Literal["written", "skipped", "failed", "checked"]
    episodes: int = 0
    frames: int = 0
    message: str = ""


@dataclass
class IngestReport:
    store: str
    inputs: list[InputReport] = field(default_factory=list)

    @property
    def failed(self) -> list[InputReport]:
        return [r for r in self.inputs if r.status == "failed"]


def detect_format(path: Path) -> Format:
    name = path.name.lower()
    if name.endswith((".zarr", ".zarr.zip")) or (path / ".zgroup").exists() or (path / "zarr.json").exists():
        return "zarr"
    if name.endswith((".hdf5", ".h5", ".hdf")):
        return "hdf5"
    if name.endswith((".bag", ".mcap", ".db3")) or (path / "metadata.yaml").exists():
        return "ros"
    if not path.exists():
        raise SefaInputError("no such file or directory", file=str(path))
    raise SefaInputError("unknown input format (expected .bag, .mcap, a ROS 2 bag directory, "
                         ".hdf5, .zarr or .zarr.zip)", file=str(path))


def open_recording(path: Path, fmt: Format, options: IngestOptions, tmap: TopicMap | None
                   ) -> Recording:
    if fmt == "zarr":
        from sefa_data.zarr_import import read_dp_zarr

        return read_dp_zarr(path, renames=options.renames or None, keys=options.keys)
    if fmt == "hdf5":
        return read_hdf5(path, options.hdf5)
    if tmap is None:
        raise SefaInputError("a ROS bag or MCAP file needs a topic map (--map MAP.yaml); "
                             "`sefa ingest --scaffold` writes a starter one", file=str(path))
    from sefa_data.ros_reader import read_streams  # rosbags loads slowly; only when needed

    streams, markers = read_streams(path, tmap)
    episodes = align_streams(streams, tmap, str(path), markers)
    return Recording(meta={"format": "ros", "topic_map": to_dict(tmap)}, episodes=iter(episodes))


def input_fps(fmt: Format, options: IngestOptions, tmap: TopicMap | None, rec: Recording
              ) -> float | None:
    if options.fps is not None:
        return options.fps
    if fmt == "ros" and tmap is not None:
        return tmap.fps
    return rec.meta.get("fps")


class _StoreHandle:
    """The target store, opened or created on first need, so cleanup can always reach it."""

    def __init__(self, path: Path, zarr_format: int):
        self.path, self.zarr_format = path, zarr_format
        self.store: EpisodeStore | None = None

    def existing(self) -> EpisodeStore | None:
        if self.store is None and self.path.exists():
            self.store = EpisodeStore.open(self.path, mode="a")
        return self.store

    def for_fps(self, fps: float | None, file: str) -> EpisodeStore:
        store = self.existing()
        if store is None:
            self.store = store = EpisodeStore.open_or_create(self.path, fps, self.zarr_format)
        elif fps is not None and abs(store.fps - fps) > 1e-9:
            raise SefaInputError(f"input is at {fps:g} fps but the store is at {store.fps:g}",
                                 file=file, key="fps")
        return store


def ingest(inputs: list[Path], store_path: Path, options: IngestOptions,
           log: Callable[[str], None] = lambda _: None) -> IngestReport:
    """Append every input to the store at `store_path` (created when missing)."""
    tmap = load_topic_map(options.topic_map) if options.topic_map else None
    report = IngestReport(store=str(store_path))
    handle = _StoreHandle(Path(store_path), options.zarr_format)
    try:
        for path in map(Path, inputs):
            try:
                report.inputs.append(_ingest_one(path, handle, options, tmap, log))
            except SefaInputError as e:
                e = e.with_file(str(path))
                if not options.skip_failed:
                    raise e from None
                log(f"failed: {e.line()}")
                report.inputs.append(InputReport(str(path), "failed", message=e.line()))
    finally:
        if handle.store is not None:
            handle.store.discard_if_uncommitted()
        else:  # interrupted while the store was being created
            EpisodeStore.discard_partial(handle.path)
    return report


def _ingest_one(path: Path, handle: _StoreHandle, options: IngestOptions,
                tmap: TopicMap | None, log: Callable[[str], None]) -> InputReport:
    fmt = detect_format(path)
    if not path.exists():
        raise SefaInputError("no such file or directory", file=str(path))
    fingerprint = file_fingerprint(path)
    store = handle.existing() if not options.dry_run else None
    if store is not None and store.has_source(fingerprint["sha256"]):
        log(f"skipped: {path} (sha256 {fingerprint['sha256'][:12]} is already in {handle.path})")
        return InputReport(str(path), "skipped", message="already in the store")
    rec = open_recording(path, fmt, options, tmap)
    if options.dry_run:
        episodes = list(rec.episodes)
        frames = sum(len(e) for e in episodes)
        keys = {k: (tuple(v.shape[1:]), str(v.dtype)) for k, v in episodes[0].data.items()} if episodes else {}
        log(f"would write: {path}: {len(episodes)} episodes, {frames} frames, keys "
            + ", ".join(f"{k} {s} {d}" for k, (s, d) in sorted(keys.items())))
        return InputReport(str(path), "checked", len(episodes), frames)
    store = handle.for_fps(input_fps(fmt, options, tmap, rec), str(path))
    source = {**fingerprint, "format": fmt, "reader": _jsonable(rec.meta),
              "ingest_config": _jsonable(to_dict(options))}
    result = store.append(rec.episodes, source)
    log(f"written: {path}: {result.episodes} episodes, {result.frames} frames")
    return InputReport(str(path), "written", result.episodes, result.frames)


def _jsonable(obj):
    """Reader metadata as JSON attributes accept (numpy scalars and tuples included)."""
    import json

    import numpy as np

    def default(o):
        if isinstance(o, np.generic):
            return o.item()
        if isinstance(o, np.ndarray):
            return o.tolist()
        if isinstance(o, (set, tuple)):
            return list(o)
        if isinstance(o, Path):
            return str(o)
        return repr(o)

    return json.loads(json.dumps(obj, default=default))
