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
