"""`sefa ingest`: recordings in, episodes appended to a store, one input file at a time.

Each input is one transaction: it lands whole or not at all. With `skip_failed`, a bad input is
reported and the next one is tried; without it, the first bad input stops the run (the inputs
before it stay committed, since each is complete on its own).
"""

from __future__ import annotations

import errno
import os
import stat
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable, Literal

from sefa_data.config_io import load_yaml, to_dict
from sefa_data.episode import Recording
from sefa_data.errors import SefaInputError, clip
from sefa_data.readers.hdf5 import Hdf5Options, options_from_dict, read_hdf5
from sefa_data.readers.time_align import align_streams
from sefa_data.readers.topic_map import TopicMap, load_topic_map
from sefa_data.validate import check_fps, check_key
from sefa_data.readers.dp_zarr import LAYOUT
from sefa_data.store.zarr_store import EpisodeStore, InterruptedAfterCommit, file_fingerprint

Format = Literal["zarr", "hdf5", "ros", "lerobot"]


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
    # Processes that decode camera images of ROS inputs beside the reader (see
    # sefa_data.readers.image_decode). Speed only: the store is the same with any number, so the
    # setting is not recorded in it.
    decode_workers: int = 0
    # LeRobot input: apply info.json's dtypes even where they change values (the topic map's
    # per-feature `allow_lossy_cast`; a LeRobot dataset has no map to say it in)
    allow_lossy_cast: bool = False
    # LeRobot input: do not compare what is read with the dataset's per-episode statistics
    # (for a dataset whose statistics were not recomputed after an edit)
    skip_stats_check: bool = False


@dataclass
class InputReport:
    path: str
    status: Literal["written", "skipped", "failed", "checked"]
    episodes: int = 0
    frames: int = 0
    message: str = ""
    warnings: list[str] = field(default_factory=list)  # what was skipped or dropped, and why


@dataclass
class IngestReport:
    store: str
    inputs: list[InputReport] = field(default_factory=list)

    @property
    def failed(self) -> list[InputReport]:
        return [r for r in self.inputs if r.status == "failed"]


# suffixes that name one file: a directory of that name is a mistake, not a recording
_FILE_SUFFIXES = (".hdf5", ".h5", ".hdf", ".mcap", ".db3", ".zarr.zip")
_NOT_REGULAR = ((stat.S_ISFIFO, "a FIFO (named pipe)"), (stat.S_ISCHR, "a character device"),
                (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"))


def check_input_path(path: Path) -> None:
    """What the file system says an input is, from stat alone: never opened, since opening a
    FIFO for reading blocks until a writer comes. A missing path is left to the caller's own
    "no such file" line; a symlink loop, a dangling link, a device, a FIFO or a socket, or a
    directory under a file's name, are each said as what they are."""
    path = Path(path)
    try:
        st = os.stat(path)
    except OSError as e:
        if e.errno == errno.ELOOP:
            raise SefaInputError("a symlink loop (following its links never reaches a file)",
                                 file=str(path)) from None
        if e.errno == errno.ENOENT and os.path.islink(path):
            raise SefaInputError(f"a dangling symlink (its target {os.readlink(path)} does not "
                                 "exist)", file=str(path)) from None
        if e.errno in (errno.ENOENT, errno.ENOTDIR):
            return
        raise SefaInputError(f"cannot read ({e.strerror})", file=str(path)) from None
    if stat.S_ISDIR(st.st_mode):
        name = path.name.lower()
        suffix = next((x for x in _FILE_SUFFIXES + (".bag",) if name.endswith(x)), None)
        # a ROS 2 bag is a folder (with metadata.yaml), whatever its name
        if suffix and not (suffix == ".bag" and (path / "metadata.yaml").exists()):
            raise SefaInputError(f"a directory, where a file is expected (a {suffix} recording "
                                 "is one file)", file=str(path))
        return
    for test, kind in _NOT_REGULAR:
        if test(st.st_mode):
            raise SefaInputError(f"not a regular file but {kind}; recordings are read from "
                                 "files and folders", file=str(path))


def detect_format(path: Path) -> Format:
    from sefa_data.lerobot.layout import is_lerobot

    check_input_path(path)
    name = path.name.lower()
    if is_lerobot(path):
        return "lerobot"
    if name.endswith((".zarr", ".zarr.zip")) or (path / ".zgroup").exists() or (path / "zarr.json").exists():
        return "zarr"
    if name.endswith((".hdf5", ".h5", ".hdf")):
        return "hdf5"
    if name.endswith((".bag", ".mcap", ".db3")) or (path / "metadata.yaml").exists():
        return "ros"
    if not path.exists():
        raise SefaInputError("no such file or directory", file=str(path))
    raise SefaInputError("unknown input format (expected .bag, .mcap, a ROS 2 bag directory, "
                         ".hdf5, .zarr, .zarr.zip or a LeRobot dataset folder)", file=str(path))


def scaffold_map(path: Path, fps: float | None = None) -> tuple[str, list[str]]:
    """A starter map of one recording, to edit and pass to `sefa ingest --map`: a bag's or an
    MCAP's topic map, or an HDF5 file's key map; and the notes to say after the map is written
    (a bag of which no topic could be mapped: the map is where a field is then selected)."""
    fmt = detect_format(path)
    if fmt == "hdf5":
        from sefa_data.readers.hdf5 import scaffold_key_map

        return scaffold_key_map(path, fps), []
    if fmt == "ros":
        from sefa_data.readers.ros import scaffold_topic_map_noted  # rosbags loads slowly

        text, warning = scaffold_topic_map_noted(path, fps)
        return text, [warning] if warning else []
    raise SefaInputError(f"a {'LeRobot dataset' if fmt == 'lerobot' else 'Zarr store'} "
                         "needs no map (choose keys with --key and --rename)", file=str(path))


def open_recording(path: Path, fmt: Format, options: IngestOptions, tmap: TopicMap | None,
                   hdf5: Hdf5Options | None = None) -> Recording:
    if fmt == "zarr":
        from sefa_data.readers.dp_zarr import read_dp_zarr

        return read_dp_zarr(path, renames=options.renames or None, keys=options.keys)
    if fmt == "hdf5":
        return read_hdf5(path, hdf5 or options.hdf5)
    if fmt == "lerobot":
        from sefa_data.lerobot.reader import read_lerobot

        return read_lerobot(path, keys=options.keys, renames=options.renames or None,
                            allow_lossy_cast=options.allow_lossy_cast,
                            check_stats=not options.skip_stats_check)
    if tmap is None:
        raise SefaInputError("a ROS bag or MCAP file needs a topic map (--map MAP.yaml); "
                             "`sefa ingest --scaffold` writes a starter one", file=str(path))
    from sefa_data.readers.ros import read_streams  # rosbags loads slowly; only when needed

    streams, markers = read_streams(path, tmap, options.decode_workers)
    episodes = align_streams(streams, tmap, str(path), markers)
    return Recording(meta={"format": "ros", "topic_map": to_dict(tmap)}, episodes=iter(episodes))


def input_fps(fmt: Format, options: IngestOptions, tmap: TopicMap | None, rec: Recording
              ) -> float | None:
    if options.fps is not None:
        return options.fps
    if fmt == "ros" and tmap is not None:
        return tmap.fps
    fps = rec.meta.get("fps")
    # a Zarr input's fps attribute is checked nowhere else
    return None if fps is None else check_fps(fps, key="fps attribute")


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
           log: Callable[[str], None] = lambda _: None, training_notes: bool = True
           ) -> IngestReport:
    """Append every input to the store at `store_path` (created when missing). With
    `training_notes`, say what the store means for `sefa train` (no `action`, a constant one,
    too few episodes for a validation split); a conversion, which trains nothing, says none."""
    if options.fps is not None:
        check_fps(options.fps, key="--fps")
    if options.decode_workers < 0:
        raise SefaInputError(f"decode workers must be 0 or more, got {options.decode_workers}",
                             key="--decode-workers")
    options.hdf5.validate()
    for new in options.renames.values():
        check_key(new, file="--rename")
    maps = _Maps(options)
    maps.check(inputs)
    report = IngestReport(store=str(store_path))
    handle = _StoreHandle(Path(store_path), options.zarr_format)
    path, done = None, 0
    try:
        for done, path in enumerate(map(Path, inputs), start=1):
            try:
                report.inputs.append(_ingest_one(path, handle, options, maps, log,
                                                 training_notes))
            except (SefaInputError, OSError, MemoryError, Exception) as e:
                e = _input_error(e, path)
                if not options.skip_failed:
                    raise e from None
                log(f"failed: {e.line()}")
                report.inputs.append(InputReport(str(path), "failed", message=e.line()))
    except KeyboardInterrupt as e:
        written = [r.path for r in report.inputs if r.status == "written"]
        if isinstance(e, InterruptedAfterCommit) or written:
            raise IngestInterrupted(e, Path(store_path), written, path,
                                    [str(p) for p in inputs[done:]]) from None
        raise
    finally:
        if handle.store is not None:
            handle.store.discard_if_uncommitted()
        else:  # interrupted while the store was being created
            EpisodeStore.discard_partial(handle.path)
    if handle.store is not None and not options.dry_run and training_notes:
        for note in (missing_action_note(handle.store), constant_action_note(handle.store)):
            if note:
                log(note)
    return report


# what `sefa train` trains on unless shape_meta.action.key says otherwise (sefa_model/config.py)
ACTION_KEY = "action"


def missing_action_note(store: EpisodeStore) -> str | None:
    """A store without an `action` key ingests, but `sefa train` stops on it: said at ingest,
    where the map that named the keys is at hand, not at the first training."""
    features = store.attrs.get("features") or {}
    if not features or ACTION_KEY in features:
        return None
    return (f"warning: {store.path} has no `{ACTION_KEY}` key (it has {', '.join(sorted(features))}): "
            f"`sefa train` trains on `{ACTION_KEY}`; rename the commanded feature to "
            f"`{ACTION_KEY}` in the map (or set shape_meta.action.key to one of these)")


def constant_action_note(store: EpisodeStore) -> str | None:
    """An action that never changes ingests, but a policy trained on it learns nothing (every
    chunk is that one value): said at ingest, where the input that holds it is at hand. The
    store's statistics mark each constant value (exact: low-dim stats see every frame), in the
    feature's own shape ([1, 2] as some LeRobot writers declare an action: nested lists)."""
    import numpy as np

    stats = (store.attrs.get("stats") or {}).get(ACTION_KEY) or {}
    constant = np.asarray(stats.get("constant") or [], dtype=bool).reshape(-1)
    if not constant.size or not constant.all():
        return None
    values = np.asarray(stats.get("min") or [], dtype=np.float64).reshape(-1)
    shown = ", ".join(f"{v:g}" for v in values[:8]) + (", ..." if values.size > 8 else "")
    return (f"warning: {store.path}: `{ACTION_KEY}` is constant ({shown} in all "
            f"{stats.get('count')} frames): a policy trained on it cannot learn anything; "
            + "; ".join(_action_advice(store.attrs.get("sources") or [])))


# where the action of each kind of input comes from, to check when it is constant
_ACTION_SOURCE = {
    "ros": "check that the topic map (--map) names the commanded topic and field",
    "hdf5": "check that --action-key (or the key map's action) names the commanded dataset",
    "lerobot": "check that its `action` feature is the commanded one (--rename FEATURE=action "
               "reads another feature as the action)",
    "zarr": "check that its action array is the commanded one (--rename KEY=action reads "
            "another array as the action)",
}


def _action_advice(sources: list[dict]) -> list[str]:
    """One piece of advice per input format, naming the inputs the action was read from."""
    by_format: dict[str, list[str]] = {}
    for s in sources:
        by_format.setdefault(s.get("format", ""), []).append(str(s.get("path")))
    out = []
    for fmt, paths in by_format.items():
        named = ", ".join(paths[:3]) + (f" and {len(paths) - 3} more" if len(paths) > 3 else "")
        advice = _ACTION_SOURCE.get(fmt, "check that it is the commanded action")
        out.append(f"{named}: {advice}")
    return out


class IngestInterrupted(KeyboardInterrupt):
    """A Ctrl-C after at least one input's append was committed: `line` says which inputs the
    store now holds, since "as it was before" would be false (each input is its own append)."""

    def __init__(self, e: KeyboardInterrupt, store: Path, written: list[str], current: Path | None,
                 not_read: list[str]):
        if isinstance(e, InterruptedAfterCommit):
            store = e.store  # a new store is at its final name once its first append commits
            line = (f"interrupted after the append was committed: {store} holds the new "
                    f"episodes of {current}")
            if written:
                line += f" (and of {', '.join(written)})"
        else:
            line = (f"interrupted: {store} holds the episodes of {', '.join(written)}, appended "
                    f"before the interrupt; {current} is not in it")
        if not_read:
            line += f"; not read: {', '.join(not_read)}"
        super().__init__(line)
        self.line = line


def _input_error(e: BaseException, path: Path) -> SefaInputError:
    """Any failure of one input as one line naming it (so that --skip-failed can go on)."""
    if isinstance(e, SefaInputError):
        return e.with_file(str(path))
    if isinstance(e, OSError):
        name = f" ({e.filename})" if e.filename and str(e.filename) != str(path) else ""
        return SefaInputError(f"{e.strerror or e}{name}: an operating system error while "
                              "reading or writing", file=str(path))
    if isinstance(e, MemoryError):
        return SefaInputError("out of memory while reading this input", file=str(path))
    if os.environ.get("SEFA_DEBUG"):
        raise e
    text = clip(str(e), 200)
    return SefaInputError(f"unexpected {type(e).__name__}: {text} (a bug in sefa: rerun with "
                          "SEFA_DEBUG=1 for the traceback and report it)", file=str(path))


class _Maps:
    """The --map file, read as a topic map for ROS inputs or as HDF5 options for HDF5 inputs."""

    def __init__(self, options: IngestOptions):
        self.options = options
        self.path = options.topic_map
        self._tmap: TopicMap | None = None
        self._hdf5: Hdf5Options | None = None

    def check(self, inputs: list[Path]) -> None:
        """Read the map before any input, so that a bad map fails the run at once."""
        if not self.path:
            return
        formats = set()
        for path in map(Path, inputs):
            try:
                formats.add(detect_format(path))
            except SefaInputError:
                pass  # reported for that input, in its turn
        if {"ros", "hdf5"} <= formats:
            raise SefaInputError("one --map cannot serve both ROS and HDF5 inputs; ingest them "
                                 "in two runs", file=self.path)
        if "hdf5" in formats:
            self.hdf5()
        else:
            self.topic_map()

    def topic_map(self) -> TopicMap | None:
        if self.path and self._tmap is None:
            self._tmap = load_topic_map(self.path)
        return self._tmap

    def hdf5(self) -> Hdf5Options:
        if not self.path:
            return self.options.hdf5
        if self._hdf5 is None:
            cli = self.options.hdf5
            if replace(cli, skip_bad_demos=False) != Hdf5Options():
                raise SefaInputError("give the HDF5 key map either in --map or as --hdf5-key/"
                                     "--obs-key/--action-key options, not both", file=self.path)
            mapped = options_from_dict(load_yaml(self.path), source=self.path)
            self._hdf5 = replace(mapped, skip_bad_demos=mapped.skip_bad_demos or cli.skip_bad_demos)
        return self._hdf5


def _warnings(meta: dict) -> list[str]:
    """What a reader skipped or dropped, in words (printed, and kept in the report)."""
    out = list(meta.get("warnings") or [])
    for path, why in (meta.get("skipped") or {}).items():
        out.append(f"skipped key {path}: {why}")
    if meta.get("layout") == LAYOUT:
        out += [f"not imported: data/{name} (not among the --key choices)"
                for name, k in meta.get("keys", {}).items() if k.get("key") is None]
    return out


def _ingest_one(path: Path, handle: _StoreHandle, options: IngestOptions,
                maps: _Maps, log: Callable[[str], None], training_notes: bool = True
                ) -> InputReport:
    fmt = detect_format(path)
    if not path.exists():
        raise SefaInputError("no such file or directory", file=str(path))
    fingerprint = file_fingerprint(path)
    store = handle.existing() if not options.dry_run else None
    if store is not None and store.has_source(fingerprint["sha256"]):
        log(f"skipped: {path} (sha256 {fingerprint['sha256'][:12]} is already in {handle.path})")
        return InputReport(str(path), "skipped", message="already in the store")
    tmap = maps.topic_map() if fmt == "ros" else None
    hdf5 = maps.hdf5() if fmt == "hdf5" else options.hdf5
    if fmt == "zarr" and options.topic_map:
        raise SefaInputError("--map is for ROS bags, MCAP and HDF5; a Zarr input takes --key "
                             "and --rename", file=str(path))
    if fmt == "lerobot" and options.topic_map:
        raise SefaInputError("--map is for ROS bags, MCAP and HDF5; a LeRobot dataset needs no "
                             "map", file=str(path))
    rec = open_recording(path, fmt, options, tmap, hdf5)
    warnings = _warnings(rec.meta)
    for w in warnings:
        log(f"warning: {path}: {w}")
    if options.dry_run:
        episodes = list(rec.episodes)
        frames = sum(len(e) for e in episodes)
        keys = {k: (tuple(v.shape[1:]), str(v.dtype)) for k, v in episodes[0].data.items()} if episodes else {}
        log(f"would write: {path}: {len(episodes)} episodes, {frames} frames, keys "
            + ", ".join(f"{k} {s} {d}" for k, (s, d) in sorted(keys.items())))
        return InputReport(str(path), "checked", len(episodes), frames, warnings=warnings)
    store = handle.for_fps(input_fps(fmt, options, tmap, rec), str(path))
    source = {**fingerprint, "format": fmt, "reader": _jsonable(rec.meta),
              "ingest_config": _jsonable(_recorded(options))}
    result = store.append(rec.episodes, source)
    if training_notes and not store.mask("valid").any():
        # a note, not a warning: nothing is wrong with the input (and the report's last line
        # stays the written one)
        log(f"note: {handle.path} has {len(store.episode_ends)} episode(s): too few for an "
            f"episode-level validation split (valid 0); training and `sefa eval --offline` hold "
            f"out the last windows of the episode instead (a window-level split, said again at "
            f"training); ingest more episodes for an episode-level split")
    log(f"written: {path}: {result.episodes} episodes, {result.frames} frames")
    return InputReport(str(path), "written", result.episodes, result.frames, warnings=warnings)


def _recorded(options: IngestOptions) -> dict:
    """The options a store records with each source: those that shape its data."""
    config = to_dict(options)
    del config["decode_workers"]
    return config


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
