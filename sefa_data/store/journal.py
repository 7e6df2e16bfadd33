"""The episode store's commit protocol: a write lock, an undo journal, and named fault points.

An append to a store directory is one transaction:

1. `begin`: the journal is built in ``.sefa-journal.tmp`` (the store's file list and copies of
   every file the append may rewrite) and renamed to ``.sefa-journal``: it exists whole or not
   at all. No store byte changes before that rename.
2. The append writes chunks, ``meta/`` and the attributes, then the checksum list.
3. `commit`: the journal is renamed to ``.sefa-journal.done`` (the commit point: one rename) and
   then deleted. A journal being deleted is never read again, so a kill halfway through the
   deletion leaves nothing to undo (an earlier version deleted the journal in place, and a kill
   there left a journal without its file list, which made the store unwritable).
4. `rollback` (an error, a Ctrl-C, or the next open after a kill): files that are not in the
   list are deleted and the saved copies are put back, then the journal is retired the same way
   as at a commit. Each step can be repeated, so a kill during a rollback is undone by the next.

`recover` runs these repairs at open: ``.done`` -> delete it, ``.tmp`` -> delete it (nothing was
written yet), a journal -> roll back. It runs only under the store's write lock: an flock on the
store directory, held for as long as a process has the store open for writing and released by
the kernel when that process dies, so a journal is never rolled back under a live writer.

Fault points: with ``SEFA_FAULT=<point>`` in the environment, the process kills itself with
SIGKILL when it reaches that point; with ``SEFA_FAULT=<point>:sigint`` it sends itself SIGINT
there instead (a Ctrl-C at that exact moment, for the messages an interrupt prints;
``<point>:sigterm`` sends SIGTERM, as `kill` or a job scheduler does), and with
``<point>:sigint:N`` only the Nth time it gets there (the second input of an ingest, say);
``<point>:sigint-group[:N]`` sends SIGINT to its whole process group, as a terminal's Ctrl-C
does to a shell pipeline (`sefa train | tee log`: tee gets it too); ``<point>:hang`` sleeps
there for ever (a library call that never returns, for the watchdogs); ``<point>:stop`` stops
the process there (SIGSTOP) until the test, having done what may happen meanwhile (another
process creating a file), sends SIGCONT.
The fault-injection test kills `sefa ingest` at every point in `FAULT_POINTS` and checks that
the store reads as exactly its state before or after the append. The check is one dictionary
lookup when the variable is unset.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import time
from pathlib import Path

from sefa_data.errors import SefaInputError

try:
    import fcntl
except ImportError:  # Windows: no advisory locks; one writer at a time is then the user's job
    fcntl = None  # type: ignore[assignment]

JOURNAL = ".sefa-journal"
JOURNAL_TMP = JOURNAL + ".tmp"
JOURNAL_DONE = JOURNAL + ".done"
LISTING = "listing.json"
SAVED = "files"

FAULT_ENV = "SEFA_FAULT"
FAULT_POINTS = (
    "begin.listed",        # the journal's file list is written, in its temporary directory
    "begin.saved",         # the files the append may rewrite are copied, journal not in place
    "begin.done",          # the journal is in place; no store byte has changed
    "append.images",       # image chunks of the first batch are written
    "append.data",         # every data array is written; meta/ is not
    "append.meta",         # meta/ is rewritten; the attributes are not
    "append.attrs",        # the attributes are rewritten; the checksum list is not
    "commit.checksums",    # the checksum list is written; the journal is not retired
    "commit.retired",      # the journal is renamed to .done (committed), not yet deleted
    "commit.deleting",     # the retired journal is half deleted (its file list first)
    "publish.before",      # a new store is complete in its temporary directory, not renamed
    "rollback.deleted",    # files the append added are deleted; saved copies not restored
    "rollback.restored",   # saved copies are restored; the journal is not retired
    "rollback.deleting",   # the retired journal is half deleted
)


def fault_point(name: str) -> None:
    """SIGKILL this process when SEFA_FAULT names this point, SIGINT (SIGTERM) it when
    SEFA_FAULT is ``<point>:sigint`` (``<point>:sigterm``; see the module docstring)."""
    chosen = os.environ.get(FAULT_ENV)
    if chosen is None:
        return
    if chosen == name:
        os.kill(os.getpid(), signal.SIGKILL)
    point, _, rest = chosen.partition(":")
    how, _, nth = rest.partition(":")
    if how == "hang" and point == name:
        while True:
            time.sleep(3600)
    if how == "stop" and point == name:
        os.kill(os.getpid(), signal.SIGSTOP)
    if how in ("sigint", "sigint-group", "sigterm") and point == name:
        _reached[name] = _reached.get(name, 0) + 1
        if _reached[name] == int(nth or 1):
            if how == "sigint-group":
                os.killpg(os.getpgid(0), signal.SIGINT)
            else:
                os.kill(os.getpid(), signal.SIGTERM if how == "sigterm" else signal.SIGINT)


_reached: dict[str, int] = {}  # how often each point was reached, for ``<point>:sigint:N``


def is_journal_path(rel: Path | str) -> bool:
    """Journal files are not store content: not listed, not checksummed, never rolled back."""
    return Path(rel).parts[0].startswith(JOURNAL)


# --------------------------------------------------------------------------- the write lock

_held: dict[str, int] = {}  # realpath -> fd: a process may open its own store more than once


def lock_path(path: Path) -> str:
    return os.path.realpath(path)


def try_lock(path: Path) -> bool:
    """Take the write lock of a store directory (non-blocking); True when this process holds it."""
    key = lock_path(path)
    if key in _held:
        return True
    if fcntl is None:
        return True
    fd = os.open(path, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        return False
    _held[key] = fd
    return True


def lock(path: Path) -> None:
    if not try_lock(path):
        raise SefaInputError("another process is writing to this store (its write lock is "
                             "held); wait for it to finish", file=str(path))


def moved(old: Path, new: Path) -> None:
    """The locked directory was renamed (a new store published); the fd keeps its lock.
    realpath resolves the parent only, so the old key is computed the same after the rename."""
    fd = _held.pop(lock_path(old), None)
    if fd is not None:
        _held[lock_path(new)] = fd


def unlock(path: Path) -> None:
    fd = _held.pop(lock_path(path), None)
    if fd is not None:
        os.close(fd)


# --------------------------------------------------------------------------- the journal

def _retire(directory: Path, point: str) -> None:
    """Delete a journal-like directory so that no kill can leave it half-deleted under its
    live name: one rename first, then the deletion of the renamed copy."""
    done = directory.parent / JOURNAL_DONE
    if directory != done:
        shutil.rmtree(done, ignore_errors=True)
        os.replace(directory, done)
    _delete_retired(done, point)


def _delete_retired(done: Path, point: str | None = None) -> None:
    if not done.exists():
        return
    listing = done / LISTING
    if listing.exists():
        listing.unlink()  # the file list first, as shutil.rmtree happened to do
    if point:
        fault_point(point)
    shutil.rmtree(done, ignore_errors=True)


class Journal:
    """Undo log for one append on a store directory; see the module docstring."""

    def __init__(self, root: Path):
        self.root = root
        self.dir = root / JOURNAL

    def begin(self, rewritten: list[Path]) -> set[str]:
        """Record the store's files and save the ones the append may rewrite; returns the list."""
        tmp = self.root / JOURNAL_TMP
        shutil.rmtree(tmp, ignore_errors=True)
        (tmp / SAVED).mkdir(parents=True)
        listing = sorted(str(p.relative_to(self.root)) for p in self.root.rglob("*")
                         if not is_journal_path(p.relative_to(self.root)))
        (tmp / LISTING).write_text(json.dumps(listing))
        fault_point("begin.listed")
        for p in rewritten:
            if p.is_file():
                dest = tmp / SAVED / p.relative_to(self.root)
                dest.parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(p, dest)
        fault_point("begin.saved")
        os.replace(tmp, self.dir)  # the journal exists whole, or not at all
        fault_point("begin.done")
        return set(listing)

    def commit(self) -> None:
        os.replace(self.dir, self.root / JOURNAL_DONE)  # the commit point
        fault_point("commit.retired")
        _delete_retired(self.root / JOURNAL_DONE, "commit.deleting")

    def rollback(self) -> None:
        """Put the store back as it was at `begin` (repeatable: a killed rollback is redone)."""
        if not self.dir.exists():
            shutil.rmtree(self.root / JOURNAL_TMP, ignore_errors=True)
            return
        keep = self._listing()
        for p in sorted(self.root.rglob("*"), key=lambda q: -len(q.parts)):
            rel = p.relative_to(self.root)
            if is_journal_path(rel) or str(rel) in keep:
                continue
            p.rmdir() if p.is_dir() and not p.is_symlink() else p.unlink()
        fault_point("rollback.deleted")
        saved = self.dir / SAVED
        for p in saved.rglob("*"):
            if p.is_file():
                dest = self.root / p.relative_to(saved)
                dest.parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(p, dest)
        fault_point("rollback.restored")
        _retire(self.dir, "rollback.deleting")

    def _listing(self) -> set[str]:
        try:
            listing = json.loads((self.dir / LISTING).read_text())
            if not isinstance(listing, list) or not all(isinstance(x, str) for x in listing):
                raise ValueError("not a list of paths")
        except (OSError, ValueError) as e:
            raise SefaInputError(
                f"the journal of an interrupted append is damaged ({LISTING}: "
                f"{e.strerror if isinstance(e, OSError) else e}), so the append cannot be undone; "
                "the store may hold part of that append: rebuild it from its sources",
                file=str(self.root), key=JOURNAL) from None
        return set(listing)

    def pending(self) -> bool:
        return any((self.root / n).exists() for n in (JOURNAL, JOURNAL_TMP, JOURNAL_DONE))

    def recover(self) -> None:
        """Finish or undo whatever an earlier, killed process left (call under the lock)."""
        _delete_retired(self.root / JOURNAL_DONE)
        self.rollback()
