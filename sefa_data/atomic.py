"""Atomic writes: the one place that owns how sefa replaces a file or a directory.

A reader, or a process killed mid-write, sees the old version or the new one, never half of one.
Temporary names carry the writer's pid, so two processes writing the same target (torchrun
ranks, two shells) never share a temporary file. Leftovers of a killed writer are hidden and
recognisable, ``.NAME.tmp-PID`` and ``.NAME.old-PID``; the stage runner's recovery restores an
``.old`` whose final name is missing and removes the rest.
"""
from __future__ import annotations

import json
import os
import shutil
import signal
import threading
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator


def tmp_name(path: Path) -> Path:
    path = Path(path)
    return path.with_name(f".{path.name}.tmp-{os.getpid()}")


def old_name(path: Path) -> Path:
    path = Path(path)
    return path.with_name(f".{path.name}.old-{os.getpid()}")


@contextmanager
def writing(path: Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path`` for a writer that wants a file name (safetensors,
    h5py, matplotlib); on success it replaces ``path``, on failure it is removed."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = tmp_name(path)
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_bytes(path: Path, data: bytes) -> None:
    with writing(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())  # the rename must not reach the disk before the data


def write_text(path: Path, text: str) -> None:
    write_bytes(path, text.encode())


def write_json(path: Path, value: Any, **dump: Any) -> None:
    write_text(path, json.dumps(value, **({"indent": 2} | dump)) + "\n")


def replace_dir(tmp: Path, final: Path) -> None:
    """Put the complete directory ``tmp`` at ``final``. ``os.replace`` cannot overwrite a
    non-empty directory, so the old one is first renamed aside (``.NAME.old-PID``), and put back
    if the second rename fails; a kill between the two renames leaves that ``.old`` for recovery."""
    tmp, final = Path(tmp), Path(final)
    final.parent.mkdir(parents=True, exist_ok=True)
    old = old_name(final)
    shutil.rmtree(old, ignore_errors=True)
    had_old = final.exists()
    try:  # both renames inside: a Ctrl-C between them also puts the old one back
        if had_old:
            os.replace(final, old)
        os.replace(tmp, final)
    except BaseException:
        if had_old and not final.exists() and old.exists():
            os.replace(old, final)
        raise
    shutil.rmtree(old, ignore_errors=True)


# --- interrupts held while a step must complete ---------------------------------------------------

@contextmanager
def interrupts_held(deliver: bool = True) -> Iterator[list[int]]:
    """Hold Ctrl-C, and a SIGTERM that a Python handler turns into an exception (`sefa convert`
    does), until the block ends, so that a commit or the removal of a temporary is not cut
    halfway (a second Ctrl-C, or a scheduler's SIGTERM after its Ctrl-C, once left a temporary
    store beside a finished conversion). Yields the signals received, in order; with `deliver`,
    the first is sent again once the handlers are back, ending the command as it would have.
    Holding swaps the Python handler, not the thread's signal mask: a signal the kernel hands to
    another thread (a progress bar's) runs its Python handler in the main thread all the same.
    Outside the main thread nothing can be held; a SIGTERM left to its default still ends the
    process at once (its temporaries are then a dead process's, removed by the next run)."""
    received: list[int] = []
    if threading.current_thread() is not threading.main_thread():
        yield received
        return
    held = {}
    try:
        for s in (signal.SIGINT, signal.SIGTERM):
            if callable(signal.getsignal(s)):
                held[s] = signal.signal(s, lambda signum, frame: received.append(signum))
        yield received
    finally:
        for s, handler in held.items():
            signal.signal(s, handler)
        if received and deliver:
            signal.raise_signal(received[0])


def remove_temporary(path: Path) -> bool:
    """Remove a temporary directory (or file) with interrupts held, so that a signal cannot
    leave it half removed; True when nothing is left at `path` (a file system error is not
    raised: the caller says what is left, and the owner's next run removes it)."""
    path = Path(path)
    with interrupts_held():
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path, ignore_errors=True)
        else:
            try:
                path.unlink(missing_ok=True)
            except OSError:
                pass
    return not os.path.lexists(path)


# --- publishing a new directory, never over anything -----------------------------------------------

def owned_name(path: Path, kind: str, pid: int | None = None) -> Path:
    """``.NAME.KIND-PID``: a temporary beside ``path`` that says whose it is, so that a later run
    can remove it once that process is gone (`remove_dead_temporaries`)."""
    path = Path(path)
    return path.with_name(f".{path.name}.{kind}-{os.getpid() if pid is None else pid}")


def pid_alive(pid: int) -> bool:
    """Whether process `pid` exists (a temporary's owner still running)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's live process
        return True
    return True


def remove_dead_temporaries(path: Path, kinds: tuple[str, ...]) -> list[Path]:
    """Remove the ``.NAME.KIND-PID`` temporaries beside ``path`` whose process is dead (a kill -9,
    a power cut): a live writer's are left alone. A reused pid keeps a leftover one run longer,
    never removes a live one. Returns what was removed."""
    path = Path(path)
    parent = path.parent
    removed = []
    try:
        names = os.listdir(parent)
    except OSError:  # no parent yet, or not a folder: nothing of ours can be there
        return removed
    for kind in kinds:
        prefix = f".{path.name}.{kind}-"
        for name in names:
            pid = name[len(prefix):]
            if not name.startswith(prefix) or not pid.isdigit() or int(pid) == os.getpid() \
                    or pid_alive(int(pid)):
                continue
            leftover = parent / name
            if leftover.is_dir() and not leftover.is_symlink():
                shutil.rmtree(leftover, ignore_errors=True)
            else:
                leftover.unlink(missing_ok=True)
            removed.append(leftover)
    return removed


_RENAME_NOREPLACE = 1  # linux/fs.h
_AT_FDCWD = -100


def _renameat2_noreplace(src: Path, dst: Path) -> bool:
    """renameat2(RENAME_NOREPLACE): the kernel renames only if ``dst`` does not exist, in one
    step (no window between a check and the rename). False where the C library or the file
    system lacks it (not Linux, glibc before 2.28, some network file systems)."""
    import ctypes
    import errno

    try:
        libc = ctypes.CDLL(None, use_errno=True)
        fn = libc.renameat2
    except (OSError, AttributeError):
        return False
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    if fn(_AT_FDCWD, os.fsencode(src), _AT_FDCWD, os.fsencode(dst), _RENAME_NOREPLACE) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.ENOSYS, errno.EINVAL, errno.ENOTSUP):
        return False
    raise OSError(err, os.strerror(err), str(dst))


def publish_new_dir(tmp: Path, final: Path) -> None:
    """Put the complete directory ``tmp`` at ``final``, which must not exist: raises
    FileExistsError, and touches nothing, if anything is at ``final`` (a folder, a file, a
    symlink, dangling or not), even one that appeared a moment ago. ``os.rename`` alone would
    silently replace an empty folder, and a check before it leaves a window; so the kernel's
    RENAME_NOREPLACE does it in one step. Where that is missing, ``mkdir`` claims the name
    atomically and the rename then replaces only that empty folder of ours (and fails, leaving
    it to whoever wrote into it meanwhile, if it is no longer empty)."""
    import errno

    tmp, final = Path(tmp), Path(final)
    if _renameat2_noreplace(tmp, final):
        return
    os.mkdir(final)  # FileExistsError if anything is there
    try:
        os.rename(tmp, final)
    except OSError as e:
        if e.errno in (errno.ENOTEMPTY, errno.EEXIST):
            raise FileExistsError(errno.EEXIST, "appeared while it was being written",
                                  str(final)) from None
        os.rmdir(final)
        raise
