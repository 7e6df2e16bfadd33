"""The store's commit protocol under SIGKILL at every named fault point (issue 12, build 1).

`sefa ingest` runs in a child process with SEFA_FAULT=<point>, which makes the process SIGKILL
itself when it reaches that point (no timing luck: the exit status -9 proves the point was
reached). After each kill the store must read as exactly its bytes before the append or exactly
its bytes after a clean append, and the next open for writing must recover and append.

The inputs are small robomimic-layout HDF5 files written here with h5py (images, so that image
chunks are written by the writer thread; no shared recording is small enough to run 30 times).
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import h5py
import numpy as np
import pytest

from sefa_data.ingest import IngestOptions, ingest
from sefa_data.store.journal import FAULT_ENV, FAULT_POINTS, JOURNAL
from sefa_data.store.zarr_store import EpisodeStore

REPO = Path(__file__).resolve().parents[2]
KILLED = -signal.SIGKILL

# where a kill leaves an existing store after recovery: the commit point is the journal's rename
AFTER_COMMIT = {"commit.retired", "commit.deleting"}
ROLLBACK = [p for p in FAULT_POINTS if p.startswith("rollback.")]
APPEND = [p for p in FAULT_POINTS if p.split(".")[0] in ("begin", "append", "commit")]
# a new store takes the same path up to its commit; these points are where it differs
NEW_STORE = ["append.images", "commit.checksums", "commit.retired", "commit.deleting",
             "publish.before"]


def write_demos(path: Path, seed: int, lengths=(6, 9), nan_in_last: bool = False) -> Path:
    rng = np.random.default_rng(seed)
    with h5py.File(path, "w") as f:
        for i, n in enumerate(lengths):
            g = f.create_group(f"data/demo_{i}")
            actions = rng.normal(size=(n, 2)).astype(np.float32)
            if nan_in_last and i == len(lengths) - 1:
                actions[n // 2, 0] = np.nan
            g["actions"] = actions
            g["obs/state"] = rng.normal(size=(n, 3)).astype(np.float32)
            g["obs/cam_image"] = rng.integers(0, 256, (n, 16, 16, 3), dtype=np.uint8)
    return path


def snapshot(path: Path) -> dict[str, bytes]:
    return {str(p.relative_to(path)): p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file()}


def sefa(*args, fault: str | None = None) -> subprocess.CompletedProcess:
    env = {**os.environ, FAULT_ENV: fault} if fault else dict(os.environ)
    env.pop(FAULT_ENV, None) if not fault else None
    return subprocess.run([sys.executable, "-m", "sefa_cli.main", *map(str, args)], cwd=REPO, env=env,
                          capture_output=True, text=True)


def in_parallel(jobs):
    # two cores: the children mostly import numpy and zarr, so a few at a time roughly halves it
    with ThreadPoolExecutor(max_workers=3) as pool:
        return list(pool.map(lambda job: job(), jobs))


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    root = tmp_path_factory.mktemp("faults")
    a, b = write_demos(root / "a.hdf5", 0), write_demos(root / "b.hdf5", 1, lengths=(5, 7, 4))
    bad = write_demos(root / "bad.hdf5", 2, nan_in_last=True)
    base = root / "base.zarr"
    ingest([a], base, IngestOptions(fps=10))
    after = root / "after.zarr"
    shutil.copytree(base, after)
    ingest([b], after, IngestOptions())
    fresh = root / "fresh.zarr"
    ingest([a], fresh, IngestOptions(fps=10))
    return {"root": root, "a": a, "b": b, "bad": bad, "base": base, "before": snapshot(base),
            "after": snapshot(after), "fresh": snapshot(fresh)}


def leftovers(store: Path) -> list[str]:
    return sorted(p.name for p in store.iterdir() if p.name.startswith(JOURNAL))


def test_every_point_is_exercised():
    assert sorted(set(APPEND) | set(NEW_STORE) | set(ROLLBACK)) == sorted(FAULT_POINTS)


def test_kill_at_every_point_of_an_append_to_an_existing_store(setup):
    stores = {}
    for point in APPEND:
        stores[point] = setup["root"] / f"existing-{point}.zarr"
        shutil.copytree(setup["base"], stores[point])
    results = in_parallel([lambda p=p: (p, sefa("ingest", setup["b"], "--out", stores[p], fault=p))
                           for p in APPEND])
    for point, r in results:
        assert r.returncode == KILLED, (point, r.returncode, r.stderr[-2000:])
        store = stores[point]
        # a reader recovers the store (no live writer holds the lock) and sees one whole state
        s = EpisodeStore.open(store)
        expected = "after" if point in AFTER_COMMIT else "before"
        assert snapshot(store) == setup[expected], point
        assert s.n_episodes == (5 if expected == "after" else 2)
        assert leftovers(store) == [], point
        # the next open for writing appends (or finds the source already committed)
        report = ingest([setup["b"]], store, IngestOptions())
        assert report.inputs[0].status == ("skipped" if expected == "after" else "written")
        assert snapshot(store) == setup["after"], point


def test_kill_at_every_point_of_a_new_store(setup):
    dirs = {p: setup["root"] / f"new-{p}" for p in NEW_STORE}
    for d in dirs.values():
        d.mkdir()
    results = in_parallel([lambda p=p: (p, sefa("ingest", setup["a"], "--out", dirs[p] / "s.zarr",
                                                 "--fps", 10, fault=p)) for p in NEW_STORE])
    for point, r in results:
        assert r.returncode == KILLED, (point, r.returncode, r.stderr[-2000:])
        d = dirs[point]
        # the store appears only at its commit (the rename into place): before that, nothing
        assert not (d / "s.zarr").exists(), point
        assert [p.name for p in d.iterdir()][0].startswith(".s.zarr.tmp-")
        report = ingest([setup["a"]], d / "s.zarr", IngestOptions(fps=10))
        assert report.inputs[0].status == "written"
        assert snapshot(d / "s.zarr") == setup["fresh"], point
        assert [p.name for p in d.iterdir()] == ["s.zarr"], point  # the dead temp dir is gone


def test_kill_at_every_point_of_a_rollback(setup):
    # a journal with every file of the append written: killed just before the checksum list
    torn = setup["root"] / "torn.zarr"
    shutil.copytree(setup["base"], torn)
    assert sefa("ingest", setup["b"], "--out", torn, fault="append.attrs").returncode == KILLED
    assert snapshot(torn) != setup["before"] and (torn / JOURNAL).is_dir()
    stores = {}
    for point in ROLLBACK:
        stores[point] = setup["root"] / f"rollback-{point}.zarr"
        shutil.copytree(torn, stores[point])
    # the rollback at open (`sefa inspect` opens the store and recovers it) is killed ...
    results = in_parallel([lambda p=p: (p, sefa("inspect", stores[p], fault=p)) for p in ROLLBACK])
    # ... and so is the rollback of an append that failed on bad data
    failed = setup["root"] / "failed.zarr"
    shutil.copytree(setup["base"], failed)
    results.append(("rollback.restored",
                    sefa("ingest", setup["bad"], "--out", failed, fault="rollback.restored")))
    stores["failed"] = failed
    for (point, r), key in zip(results, ROLLBACK + ["failed"]):
        assert r.returncode == KILLED, (point, r.returncode, r.stderr[-2000:])
        store = stores[key]
        assert EpisodeStore.open(store, mode="a").n_episodes == 2
        assert snapshot(store) == setup["before"], key
        assert leftovers(store) == []
