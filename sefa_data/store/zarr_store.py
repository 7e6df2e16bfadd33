"""The episode store: a Diffusion Policy ReplayBuffer layout with metadata, on Zarr.

Layout (Zarr format 2 by default, written with the zarr 3 library)::

    data/<key>                  (N, *frame_shape)  episodes concatenated along time
    meta/episode_ends           (E,) int64          cumulative exclusive ends (DP's convention)
    meta/episode_start_time_ns  (E,) int64          source time of each episode's first frame
    meta/episode_source         (E,) int32          index into the `sources` root attribute
    mask/train, valid           (E,) bool           seeded split, at least one episode in each
    mask/<filter>               (E,) bool           filter keys carried over from the source
                                                    (its own train/valid as source_train/valid)
    .zattrs                     sefa_format, fps, features, stats, sources, versions

The masks sit beside meta/, not in it: Diffusion Policy's `ReplayBuffer.copy_from_path` before
2024 (commit 27395b7) reads every member of meta/ as an array and fails on a group there.
Stores written before this layout keep their meta/mask group and are read as they are
(`integrity.mask_group`).

Chunks run along time only (images one frame per chunk, low-dim about 2 MB), Blosc compressed.
Images are uint8 HWC.

Appends are transactions (`journal`): before the first byte changes, a journal records
the store's file list and copies of every file the append may rewrite. A failure or Ctrl-C
rolls the store back to exactly its previous bytes; a hard kill leaves the journal, and the next
open rolls it back. A new store is built in a temporary directory and renamed into place on
commit. Each commit records checksums, and every open checks the store (`integrity`).
"""

from __future__ import annotations

import atexit
import contextlib
import errno
import hashlib
import os
import platform
import shutil
import signal
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import Any, Callable, Iterable

import numcodecs
import numpy as np
import zarr

from sefa_data import atomic
from sefa_data.store import journal as store_journal
from sefa_data.episode import Episode
from sefa_data.errors import SefaInputError, clip
from sefa_data.stats import first_nonfinite, image_histogram, lowdim_stats, stats_from_histogram


def _stop_zarr_io_loop() -> None:
    """zarr 3's own exit handler waits 0.2 s for its IO thread to stop and then closes the
    thread's event loop anyway: on a busy machine that prints a traceback ("Cannot close a
    running event loop") after a command that succeeded. Registered after zarr's (atexit runs
    the last registered first), this stops the loop with a patient join, so zarr's finds
    nothing left to do. Private names of zarr.core.sync: if they move, zarr's handler runs as
    before."""
    try:
        from zarr.core import sync

        loop, thread = sync.loop[0], sync.iothread[0]
        if loop is None or loop.is_closed():
            return
        with sync._get_lock():
            loop.call_soon_threadsafe(loop.stop)
            if thread is not None:
                thread.join(timeout=30)
                if thread.is_alive():
                    return  # still busy: leave it to zarr's handler
            loop.close()
            sync.loop[0] = sync.iothread[0] = None
    except (AttributeError, ImportError, RuntimeError):
        pass


atexit.register(_stop_zarr_io_loop)
from sefa_data.store.integrity import (MANIFEST, Level, broken_metadata, damaged, digest,
                                       mask_group, metadata_documents, unsafe_metadata,
                                       verify_store, write_manifest)
from sefa_data.store.journal import JOURNAL  # noqa: F401 (re-exported)
from sefa_data.store.journal import Journal, fault_point
from sefa_data.validate import check_fps, check_key

FORMAT_VERSION = 1
_LOWDIM_CHUNK_BYTES = 2 << 20
# Images are handed to the writer thread in batches of this size, so writing overlaps reading.
_IMAGE_BATCH_BYTES = 32 << 20
# Image statistics use every 4th pixel along each axis: per-channel moments and quantiles move
# by well under one grey level, at a sixteenth of the cost.
IMAGE_STATS_STRIDE = 4
_METADATA_FILES = {".zarray", ".zattrs", ".zgroup", ".zmetadata", "zarr.json"}


def is_image(frame_shape: tuple[int, ...], dtype: np.dtype) -> bool:
    return (len(frame_shape) == 3 and frame_shape[-1] in (1, 3, 4) and min(frame_shape[:2]) >= 8
            and np.dtype(dtype) == np.uint8)


# Recorded for provenance only (a store's attributes, every stage's manifest, `sefa info`), never
# part of a cache key: a numpy patch release should not retrain a policy.
RECORDED_PACKAGES = ("sefa", "torch", "numpy", "zarr", "numcodecs", "safetensors", "h5py",
                     "rosbags", "mcap", "mujoco", "robosuite", "gym-pusht", "metaworld")


def package_versions() -> dict[str, str]:
    """Python's version and those of the recorded packages that are installed."""
    out = {"python": platform.python_version()}
    for name in RECORDED_PACKAGES:
        with contextlib.suppress(metadata.PackageNotFoundError):
            out[name] = metadata.version(name)
    return out


def file_fingerprint(path: Path) -> dict[str, Any]:
    """sha256 and size of a file, or of a directory's files in sorted order (ROS2 bags, Zarr)."""
    files = [path] if path.is_file() else sorted(p for p in path.rglob("*") if p.is_file())
    if not files:
        raise SefaInputError("no such file, or an empty directory", file=str(path))
    h = hashlib.sha256()
    size = 0
    for f in files:
        if path.is_dir():
            h.update(str(f.relative_to(path)).encode() + b"\0")
        with open(f, "rb") as fh:
            while block := fh.read(1 << 22):
                h.update(block)
                size += len(block)
    return {"path": str(path), "sha256": h.hexdigest(), "size": size}


def split_masks(n_episodes: int, val_ratio: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Diffusion Policy's `get_val_mask`: seeded, at least one episode in each split when n > 1."""
    valid = np.zeros(n_episodes, dtype=bool)
    if n_episodes > 1 and val_ratio > 0:
        n_val = min(max(1, round(n_episodes * val_ratio)), n_episodes - 1)
        rng = np.random.default_rng(seed)
        valid[rng.choice(n_episodes, size=n_val, replace=False)] = True
    return ~valid, valid


# --------------------------------------------------------------------------- transactions


class InterruptedAfterCommit(KeyboardInterrupt):
    """A Ctrl-C that came while an append was being committed, raised once it is: the store
    holds the new episodes, and "nothing changed" would be false."""

    def __init__(self, store: Path):
        super().__init__(str(store))
        self.store = store


@contextlib.contextmanager
def _deferred_sigint(committed: Callable[[], BaseException] | None = None):
    """Let Ctrl-C (and a SIGTERM that a handler turns into one) arrive only after the block
    (`atomic.interrupts_held`): used while a rollback restores files, and while an append
    commits. For a commit, `committed` gives the interrupt to raise when the block completed
    (the append is in), a plain KeyboardInterrupt being for a block that failed."""
    failed = False
    with atomic.interrupts_held(deliver=False) as received:
        try:
            yield
        except BaseException:
            failed = True
            raise
        finally:
            if received:
                raise committed() if committed is not None and not failed else KeyboardInterrupt


def _short(e: BaseException) -> str:
    return clip(str(e)) or type(e).__name__


def _recover(path: Path) -> None:
    """Finish or undo what a killed append left, under the write lock (see journal)."""
    journal = Journal(path)
    if not journal.pending():
        return
    try:
        if not store_journal.try_lock(path):
            raise SefaInputError("another process is appending to this store right now (its "
                                 "journal and write lock are in place); wait for it to finish",
                                 file=str(path))
        try:
            with _deferred_sigint():
                journal.recover()
        finally:
            store_journal.unlock(path)
    except OSError as e:
        raise _os_error(e, path, "roll back the append that was interrupted here") from None


def _os_error(e: OSError, path: Path, doing: str) -> SefaInputError:
    if e.errno in (errno.EACCES, errno.EPERM, errno.EROFS):
        return SefaInputError(f"the store is read-only (cannot {doing}: {e.strerror})",
                              file=str(path))
    return SefaInputError(f"cannot {doing} ({e.strerror or e})",
                          file=str(e.filename or path))


# --------------------------------------------------------------------------- the store


@dataclass
class AppendResult:
    episodes: int
    frames: int
    skipped: bool = False  # the source's sha256 was already in the store
    source: str = ""


class EpisodeStore:
    """A Zarr episode store in the Diffusion Policy layout. Open with `open` or `create`."""

    def __init__(self, path: Path, root: zarr.Group, final_path: Path | None = None):
        self.path = path
        self.root = root
        self._final_path = final_path  # a new store lives in a temporary dir until its first commit
        self.verification: dict[str, Any] = {}  # what `open` checked

    # ---- opening

    @classmethod
    def open(cls, path: str | Path, mode: str = "r", verify: Level = "quick") -> "EpisodeStore":
        """Open a store; `verify` picks the integrity check (see `integrity`): "quick" on
        every open by default, "full" for `sefa inspect --verify`. A journal left by a killed
        append is rolled back first (in any mode, when no live process holds the write lock)."""
        path = Path(path)
        if not path.exists():
            raise SefaInputError("no such store (run `sefa ingest` first)", file=str(path))
        if not path.is_dir() or (not (path / ".zgroup").exists()
                                 and not (path / "zarr.json").exists()):
            raise SefaInputError("not a Zarr store directory (no .zgroup or zarr.json)",
                                 file=str(path))
        _recover(path)
        unsafe = unsafe_metadata(metadata_documents(path))
        if unsafe is not None:
            raise damaged(f"uses {unsafe[1]}, which sefa never decodes (it can run code)", path,
                          unsafe[0])
        try:
            root = zarr.open_group(str(path), mode="r" if mode == "r" else "r+")
            attrs = dict(root.attrs)
        except Exception as e:  # a damaged .zgroup/.zattrs (zarr raises JSON and value errors)
            bad = broken_metadata(path)
            if bad is not None:
                raise damaged("not valid JSON", path, bad) from None
            raise damaged(f"unreadable group metadata ({type(e).__name__}: {_short(e)})",
                          path) from None
        if "sefa_format" not in attrs:
            raise SefaInputError("not a sefa store (no sefa_format attribute); import it with "
                                 "`sefa ingest` instead", file=str(path))
        store = cls(path, root)
        store.verification = verify_store(path, root, attrs, FORMAT_VERSION, verify)
        return store

    @classmethod
    def create(cls, path: str | Path, fps: float, zarr_format: int = 2) -> "EpisodeStore":
        """A new, empty store; it appears at `path` only when the first append commits."""
        path = Path(path)
        check_fps(fps, file=str(path))
        if path.exists():
            raise SefaInputError("already exists", file=str(path))
        cls._remove_stale_partials(path)
        creating = cls._being_created(path)
        if creating:  # two ingests into one new store: say so, not a missing journal file
            raise SefaInputError(f"another process (pid {creating[0]}) is creating this store; "
                                 "run this ingest again once it has finished (it then appends)",
                                 file=str(path))
        tmp = cls._partial(path)
        shutil.rmtree(tmp, ignore_errors=True)
        try:  # a Ctrl-C in here comes before the caller holds the store that would clean up
            tmp.mkdir(parents=True)
            store_journal.lock(tmp)  # held until the first commit publishes it (or discard)
            with zarr.config.set({"array.write_empty_chunks": True}):
                root = zarr.open_group(str(tmp), mode="w", zarr_format=zarr_format)
                root.create_group("data")
                root.create_group("meta")
                root.create_group("mask")
                root.update_attributes({"sefa_format": FORMAT_VERSION, "fps": float(fps),
                                        "features": {}, "stats": {}, "image_histograms": {},
                                        "sources": [], "split": {"val_ratio": 0.1, "seed": 42}})
        except BaseException as e:
            store_journal.unlock(tmp)
            shutil.rmtree(tmp, ignore_errors=True)
            if isinstance(e, OSError):
                raise _os_error(e, path.parent, "create a store here") from None
            raise
        return cls(tmp, root, final_path=path)

    @staticmethod
    def _partial(path: Path) -> Path:
        """Where this process builds a new store until its first append commits."""
        return atomic.tmp_name(path)

    @staticmethod
    def _remove_stale_partials(path: Path) -> None:
        """New stores of killed processes: their write lock died with them. One whose process
        lives may be in the instant between its mkdir and its lock: it stays (issue 25: a
        second ingest deleted it, and the first then failed on its own journal file)."""
        for p in path.parent.glob(f".{path.name}.tmp-*"):
            with contextlib.suppress(OSError):
                if p.is_dir() and not _creator_alive(p) and store_journal.try_lock(p):
                    shutil.rmtree(p, ignore_errors=True)
                    store_journal.unlock(p)

    @staticmethod
    def _being_created(path: Path) -> list[int]:
        """The pids of other live processes that are creating a new store at `path` (their
        temporary store is locked)."""
        pids = []
        for p in path.parent.glob(f".{path.name}.tmp-*"):
            pid = _creator(p)
            if pid is not None and pid != os.getpid() and _creator_alive(p):
                with contextlib.suppress(OSError):
                    if not store_journal.try_lock(p):
                        pids.append(pid)
                    else:
                        store_journal.unlock(p)
        return pids

    @classmethod
    def discard_partial(cls, path: str | Path) -> None:
        """Remove this process's uncommitted new store for `path`, if there is one (for callers
        interrupted before `create` returned the store to them)."""
        tmp = cls._partial(Path(path))
        store_journal.unlock(tmp)
        shutil.rmtree(tmp, ignore_errors=True)

    @classmethod
    def open_or_create(cls, path: str | Path, fps: float | None, zarr_format: int = 2
                       ) -> "EpisodeStore":
        path = Path(path)
        if path.exists():
            store = cls.open(path, mode="a")
            if fps is not None and abs(store.fps - fps) > 1e-9:
                raise SefaInputError(f"the store is at {store.fps:g} fps, the input asks for {fps:g}",
                                     file=str(path), key="fps")
            return store
        if fps is None:
            raise SefaInputError("a new store needs an fps (give --fps or set it in the map)",
                                 file=str(path), key="fps")
        return cls.create(path, fps, zarr_format)

    # ---- reading

    @property
    def fps(self) -> float:
        return float(self.root.attrs["fps"])

    @property
    def attrs(self) -> dict[str, Any]:
        return dict(self.root.attrs)

    @property
    def keys(self) -> list[str]:
        return sorted(self.root["data"].array_keys())

    @property
    def episode_ends(self) -> np.ndarray:
        meta = self.root["meta"]
        return meta["episode_ends"][:] if "episode_ends" in meta else np.zeros(0, np.int64)

    @property
    def n_episodes(self) -> int:
        return len(self.episode_ends)

    @property
    def n_frames(self) -> int:
        ends = self.episode_ends
        return int(ends[-1]) if len(ends) else 0

    @property
    def episode_lengths(self) -> np.ndarray:
        return np.diff(self.episode_ends, prepend=0)

    def mask(self, name: str) -> np.ndarray:
        return mask_group(self.root)[name][:]

    def mask_names(self) -> list[str]:
        return sorted(mask_group(self.root).array_keys())

    def get_episode(self, i: int, keys: list[str] | None = None) -> dict[str, np.ndarray]:
        ends = self.episode_ends
        start = int(ends[i - 1]) if i > 0 else 0
        return {k: self.root["data"][k][start:int(ends[i])] for k in (keys or self.keys)}

    def has_source(self, sha256: str) -> dict | None:
        return next((s for s in self.root.attrs["sources"] if s["sha256"] == sha256), None)

    # ---- appending

    def append(self, episodes: Iterable[Episode], source: dict[str, Any]) -> AppendResult:
        """Write all `episodes` of one source, or nothing. `source` is its provenance record.

        Runs under the store's write lock, on a fresh view of the store (another process may
        have appended since this one opened it)."""
        new = self._final_path is not None
        if not new:
            try:
                store_journal.lock(self.path)
            except OSError as e:
                raise _os_error(e, self.path, "lock the store for writing") from None
        try:
            return self._append_locked(episodes, source)
        finally:
            if not new:
                store_journal.unlock(self.path)

    def _append_locked(self, episodes: Iterable[Episode], source: dict[str, Any]) -> AppendResult:
        self.root = zarr.open_group(str(self.path), mode="r+")
        if self.has_source(source["sha256"]):
            return AppendResult(0, 0, skipped=True, source=source["path"])
        journal = Journal(self.path)
        rewritten = self._files_an_append_rewrites()
        try:
            before = journal.begin(rewritten)
        except BaseException as e:
            with _deferred_sigint():
                with contextlib.suppress(OSError):
                    journal.rollback()
            if isinstance(e, OSError):
                raise _os_error(e, self.path, "start an append") from None
            raise
        try:
            # every chunk is written, even one equal to the fill value, so that a chunk file
            # that is missing always means damage (zarr would read it as zeros)
            with zarr.config.set({"array.write_empty_chunks": True}):
                self.root = zarr.open_group(str(self.path), mode="r+")
                with _Appender(self) as appender:
                    result = appender.run(episodes, source)
            fault_point("append.attrs")
            write_manifest(self.path, before,
                           [str(p.relative_to(self.path)) for p in rewritten], appender.digests)
            fault_point("commit.checksums")
        except BaseException:
            with _deferred_sigint():
                journal.rollback()
                self.root = zarr.open_group(str(self.path), mode="r+")  # drop stale in-memory state
            raise
        with _deferred_sigint(committed=lambda: InterruptedAfterCommit(self.path)):
            journal.commit()
            if self._final_path is not None:
                fault_point("publish.before")
                try:  # the commit point of a new store
                    os.replace(self.path, self._final_path)
                except OSError as e:
                    self.discard_if_uncommitted()
                    raise SefaInputError(f"cannot put the new store in place ({e.strerror}); "
                                         "did another process create it meanwhile?",
                                         file=str(self._final_path)) from None
                store_journal.moved(self.path, self._final_path)
                store_journal.unlock(self._final_path)
                self.path, self._final_path = self._final_path, None
                self.root = zarr.open_group(str(self.path), mode="r+")
        return result

    def discard_if_uncommitted(self) -> None:
        """Remove a new store's temporary directory when no append ever committed."""
        if self._final_path is not None:
            store_journal.unlock(self.path)
            shutil.rmtree(self.path, ignore_errors=True)

    def _files_an_append_rewrites(self) -> list[Path]:
        """Metadata, everything under meta/, the checksum list, and the last (possibly partial)
        chunk of each array."""
        files = [p for p in self.path.rglob("*") if p.name in _METADATA_FILES
                 and not store_journal.is_journal_path(p.relative_to(self.path))]
        files += [p for p in (self.path / "meta").rglob("*") if p.is_file()]
        files += [p for p in (self.path / "mask").rglob("*") if p.is_file()]
        if (self.path / MANIFEST).exists():
            files.append(self.path / MANIFEST)
        data = self.root["data"]
        for key in data.array_keys():
            arr = data[key]
            if arr.shape[0] % arr.chunks[0]:
                last = str(arr.shape[0] // arr.chunks[0])
                adir = self.path / "data" / key
                # format 2 names chunks "3.0.0"; format 3 "c/3/0/0"
                files += [p for p in adir.iterdir() if p.name == last or p.name.startswith(last + ".")]
                c = adir / "c" / last
                files += [c] if c.is_file() else [p for p in c.rglob("*") if p.is_file()]
        return files

    def _check_episode(self, ep: Episode, features: dict, n: int) -> None:
        where = f"episode {n}" + (f" ({ep.label})" if ep.label else "")
        for key, arr in ep.data.items():
            check_key(key, file=ep.source)
            if not isinstance(arr, np.ndarray) or arr.ndim == 0:
                raise SefaInputError("a single value where one row per frame is expected",
                                     file=ep.source, key=key, where=where)
            if arr.dtype.kind not in "biuf":
                raise SefaInputError(f"{arr.dtype} values: sefa stores numbers (bool, int, "
                                     "uint, float) only", file=ep.source, key=key, where=where)
        if len(ep) == 0:
            raise SefaInputError("empty episode (no frames)", file=ep.source, where=where)
        for key, arr in ep.data.items():
            if arr.shape[0] != len(ep):
                raise SefaInputError(f"{arr.shape[0]} frames where the episode has {len(ep)}",
                                     file=ep.source, key=key, where=where)
            bad = first_nonfinite(arr)
            if bad is not None:
                raise SefaInputError("NaN or Inf value", file=ep.source, key=key,
                                     where=f"{where}, frame {bad}")
        if not features:
            return
        if set(ep.data) != set(features):
            extra = sorted(set(ep.data) - set(features))
            missing = sorted(set(features) - set(ep.data))
            what = (f"key not in the store (store keys: {', '.join(sorted(features))})" if extra
                    else "key missing from this input but present in the store")
            raise SefaInputError(what, file=ep.source, key=(extra or missing)[0], where=where)
        for key, arr in ep.data.items():
            f = features[key]
            if list(arr.shape[1:]) != f["shape"] or str(arr.dtype) != f["dtype"]:
                raise SefaInputError(
                    f"shape {tuple(arr.shape[1:])} {arr.dtype} where the store has "
                    f"{tuple(f['shape'])} {f['dtype']}", file=ep.source, key=key, where=where)

    def _declare(self, ep: Episode) -> dict:
        """Features from the first episode's keys, shapes and dtypes; image arrays are created
        now (they are written while reading), low-dim ones with their data at the end."""
        features = {}
        for key, arr in sorted(ep.data.items()):
            frame = tuple(arr.shape[1:])
            image = is_image(frame, arr.dtype)
            features[key] = {"dtype": str(arr.dtype), "shape": list(frame),
                             "names": ep.names.get(key), "type": "image" if image else "low_dim"}
            if image:
                self._create_data_array(key, features[key], np.zeros((0,) + frame, arr.dtype))
        return features

    def _create_data_array(self, key: str, feature: dict, data: np.ndarray) -> zarr.Array:
        frame = tuple(feature["shape"])
        if feature["type"] == "image":
            chunk, cname, shuffle = 1, "lz4", numcodecs.Blosc.NOSHUFFLE
        else:
            chunk = max(1, _LOWDIM_CHUNK_BYTES // max(1, data[0].nbytes if len(data) else 1))
            cname, shuffle = "zstd", numcodecs.Blosc.BITSHUFFLE
        if self.root.metadata.zarr_format == 2:
            codecs: Any = numcodecs.Blosc(cname=cname, clevel=5, shuffle=shuffle)
        else:
            codecs = [zarr.codecs.BloscCodec(cname=cname, clevel=5, shuffle="bitshuffle"
                                             if shuffle == numcodecs.Blosc.BITSHUFFLE else "noshuffle")]
        group = self.root["data"]
        if len(data):
            return group.create_array(key, data=data, chunks=(chunk,) + frame, compressors=codecs)
        return group.create_array(key, shape=data.shape, dtype=data.dtype, chunks=(chunk,) + frame,
                                  compressors=codecs)


class _Appender:
    """One append's writing: images go out in a writer thread as episodes arrive (overlapping
    the reader), low-dimensional keys are gathered and written once at the end, and every zarr
    call is counted, because with zarr-python 3 each costs milliseconds."""

    def __init__(self, store: EpisodeStore):
        self.store = store
        self.attrs = dict(store.root.attrs)
        self.data = store.root["data"]
        self.meta = store.root["meta"]
        self.arrays = {k: self.data[k] for k in self.data.array_keys()}
        self.features = dict(self.attrs["features"])
        self.histograms = {k: np.asarray(v, dtype=np.int64)
                           for k, v in self.attrs["image_histograms"].items()}
        self.old_frames = next(iter(self.arrays.values())).shape[0] if self.arrays else 0
        self.lowdim: dict[str, list[np.ndarray]] = {}
        self.images: list[Episode] = []
        self.image_bytes = 0
        self.writer = ThreadPoolExecutor(max_workers=1)
        self.writes: list = []
        self.digests: dict[str, tuple[int, str]] = {}  # image chunks hashed as they are written

    def __enter__(self) -> "_Appender":
        return self

    def __exit__(self, *exc) -> None:
        # never leave a write running behind a rollback
        self.writer.shutdown(wait=True, cancel_futures=True)

    def run(self, episodes: Iterable[Episode], source: dict[str, Any]) -> AppendResult:
        meta_names = set(self.meta.array_keys())
        old_ends = self.meta["episode_ends"][:] if "episode_ends" in meta_names else np.zeros(0, np.int64)
        first = len(old_ends)
        ends = list(old_ends)
        starts_ns = list(self.meta["episode_start_time_ns"][:]) if first else []
        source_idx = list(self.meta["episode_source"][:]) if first else []
        masks = mask_group(self.store.root)
        mask_names = set(masks.array_keys())
        filters = {n: list(masks[n][:]) for n in mask_names if n not in ("train", "valid")}
        index = len(self.attrs["sources"])
        for n, ep in enumerate(episodes):
            self.store._check_episode(ep, self.features, n)
            if not self.features:
                self.features = self.store._declare(ep)
                self.arrays = {k: self.data[k] for k in self.data.array_keys()}
            self._add(ep)
            ends.append((ends[-1] if ends else 0) + len(ep))
            starts_ns.append(ep.start_time_ns)
            source_idx.append(index)
            # a source's own train/valid lists (robomimic's filter keys) are kept beside the
            # store's seeded split, never in its place
            ep_filters = {f"source_{f}" if f in ("train", "valid") else f for f in ep.filters}
            for f in ep_filters | set(filters):
                filters.setdefault(f, [False] * (len(ends) - 1)).append(f in ep_filters)
        if len(ends) == first:
            raise SefaInputError("no episodes in this input", file=source["path"])
        self._write_images()
        for future in self.writes:
            self.digests.update(future.result())
        new_lowdim = self._write_lowdim(int(ends[-1]))
        fault_point("append.data")

        _put_small(self.meta, "episode_ends", np.asarray(ends, np.int64), meta_names)
        _put_small(self.meta, "episode_start_time_ns", np.asarray(starts_ns, np.int64), meta_names)
        _put_small(self.meta, "episode_source", np.asarray(source_idx, np.int32), meta_names)
        split = self.attrs["split"]
        train, valid = split_masks(len(ends), split["val_ratio"], split["seed"])
        for name, values in {"train": train, "valid": valid, **filters}.items():
            _put_small(masks, name, np.asarray(values, bool), mask_names)
        fault_point("append.meta")

        source = {**source, "episodes": [first, len(ends) - first]}
        self.store.root.update_attributes({
            "features": self.features,
            "image_histograms": {k: v.tolist() for k, v in self.histograms.items()},
            "stats": self._stats(new_lowdim),
            "sources": list(self.attrs["sources"]) + [source],
            "versions": package_versions(),
        })
        return AppendResult(len(ends) - first, int(ends[-1]) - self.old_frames, source=source["path"])

    def _add(self, ep: Episode) -> None:
        for key, arr in ep.data.items():
            if self.features[key]["type"] != "image":
                self.lowdim.setdefault(key, []).append(arr)
        if any(f["type"] == "image" for f in self.features.values()):
            self.images.append(ep)
            self.image_bytes += sum(a.nbytes for a in ep.data.values())
            if self.image_bytes >= _IMAGE_BATCH_BYTES:
                self._write_images()

    def _write_images(self) -> None:
        """Hand the gathered image frames to the writer thread (one zarr resize per key)."""
        if not self.images:
            return
        for key, f in self.features.items():
            if f["type"] != "image":
                continue
            arr = self.arrays[key]
            block = np.concatenate([ep.data[key] for ep in self.images])
            n = arr.shape[0]
            arr.resize((n + len(block),) + arr.shape[1:])
            h = image_histogram(block[:, ::IMAGE_STATS_STRIDE, ::IMAGE_STATS_STRIDE])
            self.histograms[key] = self.histograms[key] + h if key in self.histograms else h
            if _one_frame_chunks_v2(arr):
                self.writes.append(self.writer.submit(_write_frame_chunks, arr, self.store.path,
                                                      f"data/{key}", n, block))
            else:
                arr[n:] = block
                fault_point("append.images")
        self.images, self.image_bytes = [], 0

    def _write_lowdim(self, total: int) -> dict[str, np.ndarray]:
        out = {}
        for key, parts in self.lowdim.items():
            block = np.concatenate(parts)
            if key not in self.arrays:  # a new store: one zarr call creates and fills it
                self.arrays[key] = self.store._create_data_array(key, self.features[key], block)
            else:
                arr = self.arrays[key]
                arr.resize((total,) + arr.shape[1:])
                arr[self.old_frames:] = block
            out[key] = block
        return out

    def _stats(self, new_lowdim: dict[str, np.ndarray]) -> dict[str, dict]:
        out = {}
        for key, f in self.features.items():
            if f["type"] == "image":
                out[key] = stats_from_histogram(self.histograms[key]).to_json()
            else:  # low-dim stats are exact, so they need every frame, old ones included
                values = new_lowdim[key] if self.old_frames == 0 else self.arrays[key][:]
                out[key] = lowdim_stats(values).to_json()
        return out


def _one_frame_chunks_v2(arr: zarr.Array) -> bool:
    meta = arr.metadata
    return (meta.zarr_format == 2 and arr.chunks[0] == 1 and arr.chunks[1:] == arr.shape[1:]
            and not meta.filters and meta.order == "C")


def _write_frame_chunks(arr: zarr.Array, root: Path, prefix: str, start: int,
                        block: np.ndarray) -> dict[str, tuple[int, str]]:
    """Write one-frame chunks of a Zarr format 2 array as files, with the array's own codec.

    zarr-python 3 spends about 1 ms of Python per chunk on its async machinery, which for
    images (one chunk per frame) is 20 times the cost of compressing and writing the frame.
    A format 2 chunk is just the compressed C-order bytes under the key "i.0.0.0"; reading
    back through zarr is what the tests check. Returns each chunk's size and checksum, taken
    from the bytes written, so that the commit does not read them back.
    """
    directory = root / prefix
    digests = {}
    sep = arr.metadata.dimension_separator
    rest = sep.join("0" for _ in arr.shape[1:])
    codec = arr.metadata.compressor
    for i, frame in enumerate(block, start=start):
        path = directory / f"{i}{sep}{rest}"
        if sep == "/":
            path.parent.mkdir(parents=True, exist_ok=True)
        encoded = codec.encode(np.ascontiguousarray(frame)) if codec else frame.tobytes()
        # os-level calls: a Python file object per frame holds the GIL long enough to slow the
        # reader thread measurably (tens of thousands of files per store)
        view = memoryview(encoded).cast("B")
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        try:
            written = os.write(fd, view)
            if written != view.nbytes:
                raise OSError(errno.ENOSPC, f"short write ({written} of {view.nbytes} bytes)",
                              str(path))
        finally:
            os.close(fd)
        digests[f"{prefix}/{i}{sep}{rest}"] = (view.nbytes, digest(view))
    fault_point("append.images")
    return digests


def _put_small(group: zarr.Group, name: str, values: np.ndarray, existing: set[str]) -> None:
    """(Re)write a small per-episode array, kept in one chunk for up to 65536 episodes.

    `existing` holds the names already in `group`, so that no zarr call is spent asking.
    """
    if name not in existing:
        group.create_array(name, data=values, chunks=(max(1 << 16, len(values)),))
        return
    arr = group[name]
    arr.resize(values.shape)
    arr[:] = values



def _creator(tmp: Path) -> int | None:
    """The pid in a new store's temporary name (sefa_data/atomic.py's tmp_name)."""
    pid = tmp.name.rsplit("-", 1)[-1]
    return int(pid) if pid.isdigit() else None


def _creator_alive(tmp: Path) -> bool:
    pid = _creator(tmp)
    if pid is None or pid == os.getpid():
        return False
    return atomic.pid_alive(pid)
