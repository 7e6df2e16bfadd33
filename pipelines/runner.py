"""The cached stage runner behind `sefa run`, `sefa status` and every single-stage command.

A workspace holds one run folder per (stage config, inputs): ``runs/train/<run id>/``,
``runs/align/<run id>/``, each with a ``manifest.json`` that records what it was built from, and
one pointer per stage (``train``, ``reflow/iter_1``, ``align``: relative symlinks) to the run
the workspace currently uses. A stage is skipped when the current run still matches (same config
hash, same input fingerprints); when another kept run matches, the pointer moves back to it. A
new run never deletes an old one (``--force`` rebuilds the run of the same key in place), so
sweeps sit side by side. There is no ML in this module; a stage is just a function that fills a
directory.

Guarantees:

- An artifact is never half-written where it is read. A stage writes into
  ``runs/<artifact>/.<run id>.partial``, ``manifest.json`` is written last, the finished folder
  is renamed into place and the pointer is swapped with one rename. A crash, Ctrl-C or SIGKILL
  leaves the previous artifact as it was. A partial folder that holds a training checkpoint is
  kept: the next build of the same run id resumes from it (same config, same inputs).
- Manifests name workspace files relative to the workspace (``./dataset.zarr``), so a copied or
  moved workspace stays cached.
- Invalidation flows downstream by itself. A downstream stage fingerprints an upstream artifact by
  the hash of its manifest, and every rerun writes a different manifest (a fresh ``build_id``;
  ``run_id`` is the run folder's name).
- One writer at a time. ``Workspace.lock()`` takes an ``flock`` on ``.sefa/lock``; the kernel
  drops it when the holder dies, so a killed run never leaves a stale lock behind.

Under torchrun every rank runs the same command. Rank 0 alone takes the lock, judges the cache
(``decide``, as one process does), creates the temporary directory and writes the manifest; it
broadcasts its decision, so every rank skips or runs the same stages. A ``parallel`` stage (training, coupling generation) is run
by every rank into rank 0's temporary directory (the stage writes from rank 0 only); any other
stage runs on rank 0 while the others wait. The manifests are the same as one process's, so
``sefa status`` and later single-process stages reuse a distributed run. Several nodes need the
workspace on a shared filesystem.

Package versions and the git SHA are recorded in each manifest, but they are not part of the
cache key: a numpy patch release should not retrain a policy. ``--force`` reruns a stage when a
user suspects an upgrade matters.
"""

from __future__ import annotations

import fcntl
import glob
import hashlib
import json
import os
import shutil
import subprocess
import time
import uuid
from contextlib import contextmanager
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Callable, Collection, Iterator, Literal

from sefa_data.errors import NonFiniteError, SefaInputError
from sefa_data import atomic
from sefa_data.store.journal import fault_point
from sefa_data.store.zarr_store import package_versions

MANIFEST = "manifest.json"
COMPLETE = "complete"
STATE_DIR = ".sefa"
RUNS_DIR = "runs"
PARTIAL = ".partial"
# In a kept `.partial`: the seconds its earlier segments ran, so that a resumed run's duration is
# the whole run's (removed when the run completes; the manifest records the segments)
SEGMENTS = ".sefa-segments.json"

# A file modified this recently may still change within its filesystem's timestamp granularity
# (1 s on some network filesystems, 2 s on FAT) without its size or mtime changing, so its hash
# is not cached ("racy" entries, as git calls them); it is simply rehashed next time.
_RACY_WINDOW_NS = 2_000_000_000
_CHUNK = 1 << 20

State = Literal["cached", "stale", "missing", "running"]
Log = Callable[[str], None]


@dataclass
class Stage:
    """One step of the pipeline.

    ``inputs`` are upstream artifact names (relative, e.g. ``"reflow/iter_1"``) or absolute paths
    to files or directories. ``run`` receives an empty directory to fill and returns a JSON-able
    summary that is stored in the manifest.
    """

    name: str
    artifact: str
    config: dict[str, Any]
    inputs: list[str]
    run: Callable[[Path], dict[str, Any]]
    parallel: bool = False  # under torchrun, every rank runs it (else rank 0 alone)
    # dotted keys of `config` that are recorded in the manifest but are not part of the cache
    # key (a training's log cadence): changing one reruns nothing
    unkeyed: tuple[str, ...] = ()
    # whether a build may start from a finished run of another key (a training asked for more
    # steps), given (that run's key, this build's key, that run's folder); see `Extension`
    extends: Callable[[dict[str, Any], dict[str, Any], str], "Extension | None"] | None = None

    def __post_init__(self) -> None:
        parts = Path(self.artifact).parts
        # Leading dots are reserved for .sefa/ and the runner's temp directories.
        if (not parts or Path(self.artifact).is_absolute()
                or any(p in ("", ".", "..") or p.startswith(".") for p in parts)):
            raise ValueError(f"stage {self.name}: artifact must be a plain relative path, "
                             f"got {self.artifact!r}")


@dataclass(frozen=True)
class Extension:
    """A finished run that a build may continue instead of starting over: `allowed` (else the
    build starts over and says why), `exact` (the result is the same as a build from scratch)
    and what it means, in words, for the log."""

    allowed: bool
    exact: bool
    note: str


@dataclass(frozen=True)
class StageStatus:
    state: State
    reason: str


@dataclass(frozen=True)
class StageResult:
    name: str
    ran: bool
    manifest: dict[str, Any]


# --- hashing -------------------------------------------------------------------------------------

def canonical_json(value: Any) -> str:
    """The one serialization that config hashes are taken over: key order must not matter."""
    return json.dumps(value, sort_keys=True, separators=(",", ":"), ensure_ascii=False,
                      allow_nan=False)


def config_hash(config: dict[str, Any]) -> str:
    return hashlib.sha256(canonical_json(config).encode()).hexdigest()


def cache_key(config: Any, unkeyed: Collection[str]) -> Any:
    """A stage config without its unkeyed (dotted) keys: what the cache compares and hashes.
    Applied to old manifests too, so a key that leaves the cache key does not make every
    existing workspace stale."""
    if not unkeyed or not isinstance(config, dict):
        return config
    out = dict(config)
    for dotted in unkeyed:
        head, _, rest = dotted.partition(".")
        if head not in out:
            continue
        if rest:
            out[head] = cache_key(out[head], [rest])
        else:
            del out[head]
    return out


def _hash_file_contents(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(_CHUNK):
            digest.update(chunk)
    return digest.hexdigest()


@dataclass
class FileHashCache:
    """sha256 of input files, keyed on (path, size, mtime_ns) so a large Zarr store is only
    stat-ed, not reread, when nothing in it changed. A touched but unchanged file is rehashed
    and gets the same digest, so it does not invalidate anything."""

    path: Path
    _entries: dict[str, dict[str, Any]] | None = field(default=None, init=False, repr=False)
    _dirty: bool = field(default=False, init=False, repr=False)
    # True while a command is still being checked: a refused command leaves .sefa/ as it was,
    # so what it hashed is saved only once it holds the lock (or never)
    held: bool = field(default=False, init=False, repr=False)

    def file_sha256(self, path: Path) -> str:
        st = path.stat()
        entries = self._load()
        key = str(path)
        hit = entries.get(key)
        if hit and hit.get("size") == st.st_size and hit.get("mtime_ns") == st.st_mtime_ns:
            return hit["sha256"]
        digest = _hash_file_contents(path)
        if time.time_ns() - st.st_mtime_ns > _RACY_WINDOW_NS:
            entries[key] = {"size": st.st_size, "mtime_ns": st.st_mtime_ns, "sha256": digest}
            self._dirty = True
        return digest

    def save(self) -> None:
        # Never create a workspace just because someone asked for its status.
        if self.held or not self._dirty or not self.path.parent.parent.is_dir():
            return
        # Atomic replace: `sefa status` may save while a locked run saves too; the last writer
        # wins and the loser's entries are merely recomputed later, never corrupted.
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            _write_json_atomic(self.path, self._entries)
        except OSError:
            # a read-only workspace (a shared or archived one, a read-only mount): the cache
            # only saves rehashing, so a read command still answers
            return
        self._dirty = False

    def _load(self) -> dict[str, dict[str, Any]]:
        if self._entries is None:
            try:
                self._entries = json.loads(self.path.read_text())
                if not isinstance(self._entries, dict):
                    self._entries = {}
            except (OSError, ValueError):
                self._entries = {}  # a lost or corrupt cache only costs a rehash
        return self._entries


def path_sha256(path: Path, cache: FileHashCache, exclude: tuple[str, ...] = ()) -> str:
    """A file's sha256; for a directory, sha256 over its sorted relative paths and file hashes
    (hashing per-file digests instead of raw bytes is what lets unchanged chunks be cached),
    the top-level files named in `exclude` left out."""
    if not path.is_dir():
        return cache.file_sha256(path)
    files = sorted(
        (Path(dirpath) / name).relative_to(path).as_posix()
        for dirpath, _, names in os.walk(path) for name in names
    )
    files = [f for f in files if f not in exclude]
    digest = hashlib.sha256()
    for rel in files:
        digest.update(f"{rel}\0{cache.file_sha256(path / rel)}\n".encode())
    return digest.hexdigest()


# --- the workspace -------------------------------------------------------------------------------

@dataclass
class Workspace:
    root: Path
    hashes: FileHashCache = field(init=False, repr=False)
    _lock_depth: int = field(default=0, init=False, repr=False)

    def __post_init__(self) -> None:
        self.root = Path(self.root).absolute()
        self.hashes = FileHashCache(self.root / STATE_DIR / "file_hashes.json")

    record: dict[str, Any] = field(default_factory=dict, repr=False)  # written into manifests

    def artifact_dir(self, artifact: str) -> Path:
        """The stage's pointer: a relative symlink to its current run (a real directory in a
        workspace made before runs were kept)."""
        return self.root / artifact

    def runs_dir(self, artifact: str) -> Path:
        return self.root / RUNS_DIR / artifact

    def run_dir(self, artifact: str, run_id: str) -> Path:
        return self.runs_dir(artifact) / run_id

    def partial_dir(self, artifact: str, run_id: str) -> Path:
        return self.runs_dir(artifact) / f".{run_id}{PARTIAL}"

    def source_key(self, source: str) -> str:
        """How a manifest names an input: artifacts by name, workspace files as ``./path``."""
        if Path(source).is_absolute():
            try:
                return "./" + Path(os.path.abspath(source)).relative_to(self.root).as_posix()
            except ValueError:
                return source
        return source

    def read_manifest(self, artifact: str) -> dict[str, Any] | None:
        """The manifest of a complete artifact, or None (a directory without a readable,
        complete manifest is not an artifact: it counts as missing)."""
        manifest = _read_json(self.artifact_dir(artifact) / MANIFEST)
        if manifest is None or manifest.get("status") != COMPLETE:
            return None
        return manifest

    def fingerprint(self, source: str) -> str | None:
        """Upstream artifacts by manifest hash, files and directories by content; None if absent."""
        if Path(source).is_absolute() or source.startswith("./"):
            path = Path(source) if Path(source).is_absolute() else self.root / source[2:]
            return path_sha256(path, self.hashes) if path.exists() else None
        # Parse and hash the same bytes: an upstream rerun may swap the file in between reads.
        try:
            raw = (self.artifact_dir(source) / MANIFEST).read_bytes()
            complete = json.loads(raw).get("status") == COMPLETE
        except (OSError, ValueError, AttributeError):
            return None
        return hashlib.sha256(raw).hexdigest() if complete else None

    def input_fingerprints(self, stage: Stage) -> dict[str, str | None]:
        try:
            return {self.source_key(source): self.fingerprint(source) for source in stage.inputs}
        finally:
            self.hashes.save()

    def status(self, stage: Stage) -> StageStatus:
        return _judge(stage, self.read_manifest(stage.artifact), self.input_fingerprints(stage),
                      self.source_key)

    def kept_run(self, stage: Stage, inputs: dict[str, str | None]) -> Path | None:
        """A complete kept run of exactly this config and these inputs, if there is one."""
        named = self.run_dir(stage.artifact, run_id(stage, inputs))
        # a run made before a key left the cache key sits in a folder named after the old key
        for run in [named] + sorted(set(self.complete_runs(stage.artifact)) - {named}):
            manifest = _read_json(run / MANIFEST)
            if manifest is None or manifest.get("status") != COMPLETE:
                continue
            if _judge(stage, manifest, inputs, self.source_key).state == "cached":
                return run
        return None

    def complete_runs(self, artifact: str) -> list[Path]:
        """The kept run folders of a stage, newest first (those with a manifest)."""
        runs = self.runs_dir(artifact)
        found = [p for p in runs.iterdir() if not p.name.startswith(".")
                 and (p / MANIFEST).is_file()] if runs.is_dir() else []
        return sorted(found, key=lambda p: (p / MANIFEST).stat().st_mtime_ns, reverse=True)

    def extension(self, stage: Stage, inputs: dict[str, str | None]
                  ) -> tuple[Path, Extension] | None:
        """The finished run of the same inputs that a build of `stage` may start from (the
        current one first, then kept ones, newest first), with what the stage says of it."""
        if stage.extends is None:
            return None
        current = os.path.basename(os.path.realpath(self.artifact_dir(stage.artifact)))
        candidates = sorted(self.complete_runs(stage.artifact), key=lambda r: r.name != current)
        wanted = stage_key(stage)
        refused = None
        for run in candidates:
            manifest = _read_json(run / MANIFEST)
            if manifest is None or manifest.get("status") != COMPLETE:
                continue
            recorded = {self.source_key(k): v for k, v in (manifest.get("inputs") or {}).items()}
            if recorded != inputs:
                continue
            ext = stage.extends(cache_key(manifest.get("config"), stage.unkeyed), wanted,
                                run.relative_to(self.root).as_posix())
            if ext is not None and ext.allowed:
                return run, ext
            refused = refused or (None if ext is None else (run, ext))
        return refused

    def lock_holder(self) -> str | None:
        """The pid of the sefa run holding the workspace lock, or None (never blocks)."""
        path = self.root / STATE_DIR / "lock"
        if not path.exists():
            return None
        fd = os.open(path, os.O_RDONLY)
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
            except BlockingIOError:
                return os.pread(fd, 32, 0).decode(errors="replace").strip() or "unknown"
            fcntl.flock(fd, fcntl.LOCK_UN)
            return None
        finally:
            os.close(fd)

    @contextmanager
    def lock(self) -> Iterator[None]:
        """Exclusive, non-blocking workspace lock; re-entrant within this Workspace object so
        that run_pipeline can hold it across the run_stage calls that also take it."""
        if self._lock_depth:
            self._lock_depth += 1
            try:
                yield
            finally:
                self._lock_depth -= 1
            return
        path = self.root / STATE_DIR / "lock"
        path.parent.mkdir(parents=True, exist_ok=True)
        # The file is never deleted: unlinking a lock file lets two processes flock two inodes.
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "unknown"
                raise SefaInputError(
                    f"another sefa run holds the workspace lock (pid {holder})",
                    file=str(path)) from None
            os.ftruncate(fd, 0)
            os.pwrite(fd, str(os.getpid()).encode(), 0)
            self._lock_depth = 1
            try:
                yield
            finally:
                self._lock_depth = 0
                os.ftruncate(fd, 0)
        finally:
            os.close(fd)  # closing releases the flock


# --- status --------------------------------------------------------------------------------------

def _judge(stage: Stage, manifest: dict[str, Any] | None,
           inputs: dict[str, str | None], source_key: Callable[[str], str] = str) -> StageStatus:
    if manifest is None:
        return StageStatus("missing", f"no complete artifact at {stage.artifact}/")
    recorded_config = manifest.get("config")
    recorded_key = cache_key(recorded_config, stage.unkeyed)
    wanted = stage_key(stage)
    if recorded_key != wanted:
        return StageStatus("stale", "config changed: " + _first_difference(
            recorded_key, wanted))
    # a manifest edited by hand; before unkeyed keys, the hash was over the whole config
    if manifest.get("config_hash") not in (config_hash(wanted), config_hash(recorded_config)):
        return StageStatus("stale", "config hash changed")
    # manifests written before inputs were recorded relative to the workspace name them absolutely
    recorded = {source_key(k): v for k, v in (manifest.get("inputs") or {}).items()}
    for source, fingerprint in inputs.items():
        if fingerprint is None:
            return StageStatus("stale", f"input {source} is missing")
        if source not in recorded:
            return StageStatus("stale", f"input {source} added")
        if recorded[source] != fingerprint:
            return StageStatus("stale", f"input {source} changed")
    for source in recorded:
        if source not in inputs:
            return StageStatus("stale", f"input {source} removed")
    return StageStatus("cached", "up to date")


def _first_difference(old: Any, new: Any, key: str = "") -> str:
    """The first differing dotted key in sorted order, e.g. ``align.eps 0.05 -> 0.1``."""
    if isinstance(old, dict) and isinstance(new, dict):
        for k in sorted(set(old) | set(new)):
            sub = f"{key}.{k}" if key else str(k)
            if k not in old:
                return f"{sub} added ({_short(new[k])})"
            if k not in new:
                return f"{sub} removed (was {_short(old[k])})"
            if old[k] != new[k]:
                return _first_difference(old[k], new[k], sub)
        return key or "(no difference)"
    return f"{key or '(whole config)'} {_short(old)} -> {_short(new)}"


def _short(value: Any, limit: int = 60) -> str:
    text = json.dumps(value, sort_keys=True)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def pipeline_status(workspace: Workspace,
                    stages: list[Stage]) -> list[tuple[str, State, str]]:
    """Each stage's status, also marking as stale what sits downstream of a stage that will
    rerun: its own manifest still matches, but the upstream manifest it keys on will change."""
    rows: list[tuple[str, State, str]] = []
    will_rerun: set[str] = set()
    for stage in stages:
        inputs = workspace.input_fingerprints(stage)
        status = _judge(stage, workspace.read_manifest(stage.artifact), inputs, workspace.source_key)
        if status.state == "cached":
            upstream = next((s for s in stage.inputs if s in will_rerun), None)
            if upstream is not None:
                status = StageStatus("stale", f"upstream {upstream} will rerun")
        elif workspace.kept_run(stage, inputs) is not None:
            status = StageStatus(status.state, status.reason + " (a kept run matches: "
                                 "switching back costs nothing)")
        elif (found := workspace.extension(stage, inputs)) is not None and found[1].allowed:
            rel = found[0].relative_to(workspace.root).as_posix()
            status = StageStatus(status.state, status.reason + f" (a build continues {rel})")
        if status.state != "cached":
            will_rerun.add(stage.artifact)
        rows.append((stage.name, status.state, status.reason))
    return rows


# --- running -------------------------------------------------------------------------------------

def run_stage(workspace: Workspace, stage: Stage, force: bool = False,
              log: Log = print) -> tuple[bool, dict[str, Any]]:
    """Run ``stage`` unless its artifact is cached; returns (ran, manifest)."""
    dist = _dist()
    if dist.distributed:
        return _run_stage_distributed(workspace, stage, force, log, dist)
    with workspace.lock():
        decision, inputs = _decide(workspace, stage, force, log)
        manifest = _settle(workspace, stage, decision, log)
        if manifest is not None:
            return False, manifest
        log(f"{stage.name}: running ({decision.reason})")
        manifest = _build(workspace, stage, inputs, log, fresh=force)
        log(f"{stage.name}: done in {manifest['duration_s']:.1f} s ({_where(workspace, stage)})")
        return True, manifest


# --- the decision --------------------------------------------------------------------------------

@dataclass(frozen=True)
class Decision:
    """What running a stage does: nothing (``cached``), point back at a kept run of the same
    key (``kept``), stop because an input is missing (``missing``), or ``build``."""

    action: Literal["cached", "kept", "missing", "build"]
    reason: str
    kept: Path | None = None


def decide(status: StageStatus, inputs: dict[str, str | None], force: bool,
           kept: Path | None) -> Decision:
    """The runner's one choice, from what it found: the current artifact's status, the input
    fingerprints and a kept run of the same key. Pure, so that under torchrun rank 0 alone
    decides and the other ranks only receive what it decided."""
    if status.state == "cached" and not force:
        return Decision("cached", status.reason)
    if kept is not None and not force:
        return Decision("kept", status.reason, kept)
    missing = [source for source, fp in inputs.items() if fp is None]
    if missing:
        return Decision("missing", f"input {missing[0]} is missing (run its stage first)")
    return Decision("build", "forced" if force else status.reason)


def _decide(workspace: Workspace, stage: Stage, force: bool,
            log: Log) -> tuple[Decision, dict[str, str | None]]:
    """Gather what `decide` needs (under the lock, after cleaning up a killed run) and decide."""
    _recover(workspace, stage, log)
    inputs = workspace.input_fingerprints(stage)
    status = _judge(stage, workspace.read_manifest(stage.artifact), inputs)
    # a kept run only matters when the current one does not match
    kept = None if force or status.state == "cached" else workspace.kept_run(stage, inputs)
    return decide(status, inputs, force, kept), inputs


def _settle(workspace: Workspace, stage: Stage, decision: Decision,
            log: Log) -> dict[str, Any] | None:
    """Carry out a decision that builds nothing and return the current manifest; None: build."""
    if decision.action == "build":
        return None
    if decision.action == "missing":
        raise SefaInputError(decision.reason, key=stage.name)
    if decision.action == "kept":
        _point(workspace, stage.artifact, decision.kept)
        log(f"{stage.name}: cached ({_where(workspace, stage)}, a kept run; now current)")
    else:
        log(f"{stage.name}: cached ({_where(workspace, stage)})")
    return workspace.read_manifest(stage.artifact) or {}


def stage_key(stage: Stage) -> Any:
    """The stage's cache key: its config as a manifest reads it back, unkeyed keys left out."""
    return cache_key(_json_roundtrip(stage, stage.config), stage.unkeyed)


def run_id(stage: Stage, inputs: dict[str, str | None]) -> str:
    """A run's folder name: its config and its inputs (what the cache keys on), 12 hex digits."""
    key = canonical_json({"config_hash": config_hash(stage_key(stage)), "inputs": inputs})
    return hashlib.sha256(key.encode()).hexdigest()[:12]


def _legacy_run_id(stage: Stage, inputs: dict[str, str | None]) -> str:
    """The folder name the same run had before its unkeyed keys left the key (the whole config
    hashed): an interrupted run from then is still continued."""
    key = canonical_json({"config_hash": config_hash(_json_roundtrip(stage, stage.config)),
                          "inputs": inputs})
    return hashlib.sha256(key.encode()).hexdigest()[:12]


def resumable_partial(workspace: Workspace, stage: Stage, inputs: dict[str, str | None]
                      ) -> Path | None:
    """The interrupted build of exactly this stage's key and inputs, if one was kept (under its
    folder name from before the unkeyed keys too)."""
    for rid in dict.fromkeys((run_id(stage, inputs), _legacy_run_id(stage, inputs))):
        partial = workspace.partial_dir(stage.artifact, rid)
        if partial.is_dir() and resumable(partial):
            return partial
    return None


def _where(workspace: Workspace, stage: Stage) -> str:
    target = workspace.artifact_dir(stage.artifact)
    if target.is_symlink():
        return f"{stage.artifact} -> {Path(os.path.realpath(target)).relative_to(workspace.root).as_posix()}"
    return stage.artifact


def run_pipeline(workspace: Workspace, stages: list[Stage], force: Collection[str] = (),
                 log: Log = print) -> list[StageResult]:
    """Run the stages in order under one lock; ``force`` names stages to rerun regardless."""
    artifacts = [s.artifact for s in stages]
    if len(set(artifacts)) != len(artifacts):
        raise ValueError(f"two stages write the same artifact: {artifacts}")
    results = []
    with _main_rank_lock(workspace):
        for stage in stages:
            ran, manifest = run_stage(workspace, stage, force=stage.name in force, log=log)
            results.append(StageResult(stage.name, ran, manifest))
    return results


def _dist():
    from sefa_model.distributed import context

    return context()


@contextmanager
def _main_rank_lock(workspace: Workspace) -> Iterator[None]:
    """The workspace lock, taken by rank 0 alone under torchrun (the ranks of one run are one
    writer; ranks on other nodes could not share an flock anyway)."""
    if _dist().is_main:
        with workspace.lock():
            yield
    else:
        yield


def _run_stage_distributed(workspace: Workspace, stage: Stage, force: bool, log: Log, dist
                           ) -> tuple[bool, dict[str, Any]]:
    """Rank 0 decides and writes; see the module docstring."""
    from sefa_model.distributed import ensure_process_group

    ensure_process_group()  # the CLI normally started it on the device the user chose
    decision: dict[str, Any] = {}
    if dist.is_main:
        with workspace.lock():
            try:
                chosen, inputs = _decide(workspace, stage, force, log)
                manifest = _settle(workspace, stage, chosen, log)
                if manifest is not None:
                    decision = {"run": False, "manifest": manifest}
                else:
                    log(f"{stage.name}: running ({chosen.reason}) on {dist.world} processes")
                    decision = {"run": True, "inputs": inputs,
                                "tmp": str(_partial(workspace, stage, inputs, log, force))}
            except SefaInputError as e:
                decision = {"error": e.what, "key": e.key, "file": e.file, "where": e.where}
    decision = dist.broadcast(decision)
    if "error" in decision:
        raise SefaInputError(decision["error"], key=decision["key"], file=decision["file"],
                             where=decision["where"])
    if not decision["run"]:
        return False, decision["manifest"]
    tmp = Path(decision["tmp"])
    manifest = None
    started, build_id = time.monotonic(), uuid.uuid4().hex
    try:
        summary = stage.run(tmp) if stage.parallel or dist.is_main else None
        dist.barrier()
        if dist.is_main:
            manifest = _finish(workspace, stage, decision["inputs"], tmp, summary, started,
                               build_id)
            log(f"{stage.name}: done in {manifest['duration_s']:.1f} s ({_where(workspace, stage)})")
    except BaseException as e:
        if dist.is_main and not (isinstance(e, KeyboardInterrupt)
                                 and _say_published(workspace, stage, tmp, build_id, e)):
            _keep_or_drop(workspace, tmp, stage, log, e, time.monotonic() - started)
        raise
    return True, dist.broadcast(manifest)  # also keeps every rank here until the rename


def resumable(partial: Path) -> bool:
    """A partial run worth keeping: it holds a training checkpoint to continue from, or a
    reflow round's finished blocks of couplings (pipelines/stages.py:COUPLING_BLOCKS)."""
    return (any(partial.glob("**/checkpoints/latest/config.json"))
            or any(partial.glob("couplings.blocks/block_*[0-9].npz")))


def _partial(workspace: Workspace, stage: Stage, inputs: dict[str, str | None], log: Log,
             fresh: bool = False) -> Path:
    """The run's build folder: the one an interrupted build of the same run id left, when it
    holds a checkpoint to resume from (same config, same inputs) that passes its checks, else
    a fresh one. `fresh` (--force) always starts over."""
    tmp = workspace.partial_dir(stage.artifact, run_id(stage, inputs))
    rel = tmp.relative_to(workspace.root).as_posix()
    legacy = resumable_partial(workspace, stage, inputs)
    if legacy is not None and legacy != tmp and not fresh and not tmp.exists():
        os.rename(legacy, tmp)  # an interrupted run of an older sefa, under today's name
    if tmp.is_dir() and resumable(tmp) and not fresh:
        _check_resumable(tmp, rel)
        log(f"{stage.name}: continuing the interrupted run in {rel}")
        return tmp
    if (tmp.exists() or tmp.is_symlink()) and not tmp.is_dir():
        log(f"{stage.name}: removed {rel}, which was not a folder")
    _remove(tmp)
    found = None if fresh else workspace.extension(stage, inputs)
    if found is not None and found[1].allowed:
        _continue_from(workspace, found[0], tmp, found[1])
    else:
        tmp.mkdir(parents=True)
    if found is not None:
        log(f"{stage.name}: {found[1].note}")
    return tmp


CONTINUED = ".continued_from.json"  # in a build folder: the finished run it continues


def _continue_from(workspace: Workspace, run: Path, tmp: Path, ext: Extension) -> None:
    """Start a build as a copy of a finished run (its manifest left out): the stage sees a run
    to resume. Copied, not linked: the continued run appends to its logs."""
    staging = tmp.with_name(tmp.name + ".copy")
    _remove(staging)
    shutil.copytree(run, staging, symlinks=True, ignore=shutil.ignore_patterns(MANIFEST, CONTINUED))
    _write_json_atomic(staging / CONTINUED, {
        "run": run.relative_to(workspace.root).as_posix(), "exact": ext.exact, "note": ext.note})
    os.rename(staging, tmp)  # a half-copied run is never taken for one to resume


def _check_resumable(tmp: Path, rel: str) -> None:
    """Every checkpoint an interrupted run would continue from passes the checks of a loaded
    one (sefa_model/policy/checkpoint.py): a damaged run is named, never continued into NaN."""
    from sefa_model.policy.checkpoint import open_checkpoint

    for latest in sorted(tmp.glob("**/checkpoints/latest")):
        try:
            open_checkpoint(latest)
        except SefaInputError as e:
            raise SefaInputError(f"the interrupted run here cannot be continued ({e.line()}); "
                                 "pass --force to start it over", file=rel) from None


@dataclass(frozen=True)
class KeptRun:
    """An interrupted build kept for its checkpoint: the stage, its folder (relative to the
    workspace) and how far it got."""

    stage: str
    path: str
    step: int | None = None
    max_steps: int | None = None
    blocks: int = 0  # a reflow round's finished blocks of couplings

    def words(self) -> str:
        """``runs/train/.<id>.partial at step 200 of 1000``, or ``... with 3 finished blocks
        of couplings``"""
        return self.path + ("" if self.step is None else
                            f" at step {self.step} of {self.max_steps}") + (
            f" with {self.blocks} finished block{'s' if self.blocks != 1 else ''} of couplings"
            if self.blocks else "")


def kept_run_of(workspace: Workspace, stage: Stage, partial: Path) -> KeptRun | None:
    """The kept interrupted build in `partial`, if it holds a checkpoint to continue from."""
    if not (partial.is_dir() and resumable(partial)):
        return None
    from sefa_model.policy.checkpoint import saved_progress

    # a reflow round's folder holds its flow's checkpoint: the one training checkpoint in it
    latest = next(iter(sorted(partial.glob("**/checkpoints/latest"))), None)
    progress = saved_progress(latest) if latest is not None else None
    blocks = len(list(partial.glob("couplings.blocks/block_*[0-9].npz")))
    return KeptRun(stage.name, partial.relative_to(workspace.root).as_posix(),
                   *(progress or (None, None)), blocks=blocks)


def _keep_or_drop(workspace: Workspace, tmp: Path, stage: Stage, log: Log,
                  error: BaseException, elapsed: float) -> None:
    """Keep an interrupted run's folder when it can be continued; a diverged one cannot (the
    same settings diverge again), so it goes. A kept run remembers the time it ran; an
    interrupt carries what was kept (`kept`) up to the line the command ends with."""
    if isinstance(error, NonFiniteError):
        shutil.rmtree(tmp, ignore_errors=True)
    elif tmp.is_dir() and resumable(tmp):
        _write_json_atomic(tmp / SEGMENTS, {"durations_s": _segments(tmp) + [round(elapsed, 3)]})
        kept = kept_run_of(workspace, stage, tmp)
        if isinstance(error, KeyboardInterrupt):
            error.kept = kept  # type: ignore[attr-defined]
        else:  # an error (a full disk, a store read that failed) is not an interrupt: say which
            log(f"{stage.name}: stopped by an error; its last checkpoint is kept: "
                f"{kept.words()} (not a complete artifact): the same command or `sefa run` "
                f"continues it")
    else:
        # a run whose manifest is written had finished its work: a Ctrl-C at that commit point
        # lost no partial work of its own (the stores are as they were: the generic line)
        finished = (tmp / MANIFEST).exists()
        shutil.rmtree(tmp, ignore_errors=True)
        if isinstance(error, KeyboardInterrupt) and not finished:
            error.lost = lost_words(stage)  # type: ignore[attr-defined]  # for the last line


def lost_words(stage: Stage) -> str | None:
    """What a Ctrl-C lost of a stage that kept nothing: a training before its first
    checkpoint, a reflow round before its first block of couplings (else None: the stage
    writes no partial work, and the stores are as they were)."""
    every = next((part["training"].get("checkpoint_every") for part in stage.config.values()
                  if isinstance(part, dict) and isinstance(part.get("training"), dict)), None)
    if every is not None:
        return (f"{stage.name} had not reached its first checkpoint (every {every} steps: "
                f"training.checkpoint_every), so nothing of it was kept")
    if isinstance(stage.config.get("couplings"), dict):  # a reflow round's first (no training)
        return (f"{stage.name} had finished no block of couplings (--block-windows sets their "
                f"size), so nothing of it was kept")
    return None


def _segments(tmp: Path) -> list[float]:
    """The durations of a kept run's earlier segments (none for a fresh run)."""
    durations = (_read_json(tmp / SEGMENTS) or {}).get("durations_s")
    return [float(d) for d in durations] if isinstance(durations, list) else []


def _build(workspace: Workspace, stage: Stage, inputs: dict[str, str | None],
           log: Log = print, fresh: bool = False) -> dict[str, Any]:
    # Fingerprints are taken before the run: if an input changes while the stage runs, the
    # recorded (older) fingerprint no longer matches and the next run redoes the stage.
    tmp = _partial(workspace, stage, inputs, log, fresh)
    started = time.monotonic()
    build_id = uuid.uuid4().hex
    try:
        return _finish(workspace, stage, inputs, tmp, stage.run(tmp), started, build_id)
    except BaseException as e:  # KeyboardInterrupt too: never a half-written artifact
        if isinstance(e, KeyboardInterrupt) and _say_published(workspace, stage, tmp, build_id, e):
            raise
        _keep_or_drop(workspace, tmp, stage, log, e, time.monotonic() - started)
        raise


def _say_published(workspace: Workspace, stage: Stage, tmp: Path, build_id: str,
                   e: KeyboardInterrupt) -> bool:
    """A Ctrl-C that came once this build's run was renamed into place: its line says so
    (whether the pointer names it yet), never "as they were before". False: it came before."""
    final = workspace.run_dir(stage.artifact, tmp.name[1:].removesuffix(PARTIAL))
    if (_read_json(final / MANIFEST) or {}).get("build_id") != build_id:
        return False
    rel = final.relative_to(workspace.root).as_posix()
    link = workspace.artifact_dir(stage.artifact)
    if os.path.realpath(link) == os.path.realpath(final):
        e.line = f"interrupted after {stage.name} was written: {stage.artifact} -> {rel} is complete"  # type: ignore[attr-defined]
    else:
        e.line = (f"interrupted: {stage.artifact} is as it was; its new run {rel} is complete, "  # type: ignore[attr-defined]
                  "and the same command switches to it")
    return True


def _finish(workspace: Workspace, stage: Stage, inputs: dict[str, str | None], tmp: Path,
            summary: Any, started: float, build_id: str) -> dict[str, Any]:
    """Write the manifest into the filled temporary directory and move it into place. Fault
    points (sefa_data.store.journal.fault_point): `stage.written` (the manifest is written, the
    run not renamed), `stage.renamed` (the run in place, the pointer not moved), `stage.pointed`."""
    config = _json_roundtrip(stage, stage.config)
    final = workspace.run_dir(stage.artifact, tmp.name[1:].removesuffix(PARTIAL))
    # a resumed run: its earlier segments count (the run's time, not its last segment's)
    segments = _segments(tmp) + [round(time.monotonic() - started, 3)]
    (tmp / SEGMENTS).unlink(missing_ok=True)
    manifest = {
        "stage": stage.name,
        "artifact": stage.artifact,
        "status": COMPLETE,
        "run_id": final.name,  # the run folder's name (its config and inputs)
        # Unique per build, so that downstream stages (keyed on this file's hash) rerun even
        # when a fast rerun reproduces every other field to the second.
        "build_id": build_id,
        "config": config,
        "config_hash": config_hash(stage_key(stage)),
        "inputs": inputs,
        "versions": package_versions(),
        "git_sha": _git_sha(),
        "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "duration_s": round(sum(segments), 3),
        **({"segments_s": segments} if len(segments) > 1 else {}),
        "processes": _dist().world,
        **workspace.record,
    }
    continued = _read_json(tmp / CONTINUED)
    if continued is not None:
        manifest["continued_from"] = continued
        (tmp / CONTINUED).unlink()
    # paths in a summary name the workspace's files relative to it, and the run's own files by
    # where they end up, not the build folder that is about to be renamed
    manifest["summary"] = _relative_paths(_json_roundtrip(stage, summary), {
        str(tmp): final.relative_to(workspace.root).as_posix(), str(workspace.root): "."})
    # Last, so that a directory without a manifest is recognisably unfinished.
    _write_json_atomic(tmp / MANIFEST, manifest)
    fault_point("stage.written")
    _swap_into_place(tmp, final)
    fault_point("stage.renamed")
    _point(workspace, stage.artifact, final)
    fault_point("stage.pointed")
    return manifest


def _relative_paths(value: Any, prefixes: dict[str, str]) -> Any:
    if isinstance(value, dict):
        return {k: _relative_paths(v, prefixes) for k, v in value.items()}
    if isinstance(value, list):
        return [_relative_paths(v, prefixes) for v in value]
    if isinstance(value, str):
        for prefix, replacement in prefixes.items():
            if value == prefix or value.startswith(prefix + os.sep):
                return replacement + value[len(prefix):]
    return value


def _point(workspace: Workspace, artifact: str, run: Path) -> None:
    """Make the stage's pointer name ``run``, with one rename (a reader sees the old or the new
    run, never neither). A real directory left by an older sefa is first kept as a run."""
    link = workspace.artifact_dir(artifact)
    link.parent.mkdir(parents=True, exist_ok=True)
    if link.is_dir() and not link.is_symlink():
        old = _read_json(link / MANIFEST) or {}
        keep = workspace.run_dir(artifact, f"kept-{(old.get('build_id') or old.get('run_id') or uuid.uuid4().hex)[:12]}")
        keep.parent.mkdir(parents=True, exist_ok=True)
        link.rename(keep)
    tmp = link.parent / f".{link.name}.link-{os.getpid()}"
    if tmp.is_symlink() or tmp.exists():
        tmp.unlink()
    tmp.symlink_to(os.path.relpath(run, link.parent))
    os.replace(tmp, link)


def _swap_into_place(tmp: Path, final: Path) -> None:
    """Two renames within one directory; at every instant either the old or the new artifact
    is complete on disk (``_recover`` puts ``.old`` back if we die between the renames)."""
    atomic.replace_dir(tmp, final)


def _recover(workspace: Workspace, stage: Stage, log: Log) -> None:
    """Clean up after a killed run. Only called under the lock, so nobody is still writing."""
    runs = workspace.runs_dir(stage.artifact)
    if runs.is_dir():
        for old in glob.glob(os.path.join(glob.escape(str(runs)), ".*.old-*")):
            final = runs / os.path.basename(old)[1:].split(".old-")[0]
            if final.exists():
                shutil.rmtree(old, ignore_errors=True)
            else:
                os.rename(old, final)
        # a continued build that was still being copied
        for copy in glob.glob(os.path.join(glob.escape(str(runs)), ".*" + PARTIAL + ".copy")):
            _remove(Path(copy))
        # a partial run without a checkpoint has nothing to resume from
        for tmp in glob.glob(os.path.join(glob.escape(str(runs)), ".*" + PARTIAL)):
            if not resumable(Path(tmp)):
                _remove(Path(tmp))
                log(f"{stage.name}: removed {os.path.basename(tmp)} left by an interrupted run")
    final = workspace.artifact_dir(stage.artifact)
    for link in glob.glob(os.path.join(glob.escape(str(final.parent)),
                                       "." + glob.escape(final.name) + ".link-*")):
        os.unlink(link)
    if not final.parent.is_dir():
        return
    prefix = os.path.join(glob.escape(str(final.parent)), "." + glob.escape(final.name))
    for old in sorted(glob.glob(prefix + ".old-*")):
        if final.exists():
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.rename(old, final)
            log(f"{stage.name}: restored the previous {stage.artifact} after an interrupted run")
    for tmp in glob.glob(prefix + ".tmp-*"):
        shutil.rmtree(tmp, ignore_errors=True)
        log(f"{stage.name}: removed {os.path.basename(tmp)} left by an interrupted run")


# --- small helpers -------------------------------------------------------------------------------

def _remove(path: Path) -> None:
    """A folder, a file or a link, whichever is there (a `.partial` need not be a folder)."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    elif path.exists() or path.is_symlink():
        path.unlink()


def _git_sha() -> str | None:
    """The checkout's commit when sefa runs from a git clone; None for an installed wheel."""
    repo = Path(__file__).resolve().parents[1]
    # Without this check an installed sefa inside some user's repository reports their commit.
    if not (repo / ".git").exists():
        return None
    try:
        done = subprocess.run(["git", "rev-parse", "HEAD"], cwd=repo, capture_output=True,
                              text=True, timeout=5, check=False)
    except (OSError, subprocess.SubprocessError):
        return None
    sha = done.stdout.strip()
    return sha if done.returncode == 0 and sha else None


def _json_roundtrip(stage: Stage, value: Any) -> Any:
    """Normalise to what a manifest reads back as (tuples become lists), rejecting non-JSON."""
    try:
        return json.loads(canonical_json(value))
    except (TypeError, ValueError) as exc:
        raise TypeError(f"stage {stage.name}: config and summary must be JSON-able ({exc})") \
            from None


def _read_json(path: Path) -> dict[str, Any] | None:
    try:
        value = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return value if isinstance(value, dict) else None


def _write_json_atomic(path: Path, value: Any) -> None:
    atomic.write_json(path, value, sort_keys=True)
