"""Checks of single values that several readers and configs share: frame rates, dataset keys,
dtypes and casts. Each raises `SefaInputError` (or `ConfigError`) with one line naming the
value, or returns why a value does not fit."""

from __future__ import annotations

import math
import os
import re

import numpy as np

from sefa_data.errors import SefaInputError

# No robot data stream runs faster than this (1 kHz torque loops exist); a larger rate is a typo
# or a unit mix-up (ns for s), and would make a grid of billions of frames.
MAX_FPS = 10_000.0
# The largest image side accepted anywhere (a 16k x 16k RGB frame is 768 MB).
MAX_IMAGE_SIDE = 16_384
_CONTROL = re.compile(r"[\x00-\x1f\x7f]")


def check_fps(value: object, *, file: str | None = None, key: str = "fps") -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.number)):
        raise SefaInputError(f"must be a number of frames per second, got {value!r}",
                             file=file, key=key)
    fps = float(value)
    if not math.isfinite(fps) or fps <= 0 or fps > MAX_FPS:
        raise SefaInputError(f"must be a positive, finite frame rate up to {MAX_FPS:g} Hz, "
                             f"got {value!r}", file=file, key=key)
    return fps


def key_problem(key: object) -> str | None:
    """Why `key` cannot be a dataset key (an array name in the store), or None."""
    if not isinstance(key, str) or not key.strip():
        return "is empty"
    if key != key.strip():
        return "has leading or trailing spaces"
    if "/" in key or "\\" in key or os.sep in key:
        return "contains a path separator"
    if key == "." or ".." in key:
        return "contains '..'"
    if key.startswith("."):
        return "starts with '.' (a hidden file name)"
    if _CONTROL.search(key):
        return "contains a control character"
    return None


def check_key(key: object, *, file: str | None = None, error: type = SefaInputError) -> str:
    why = key_problem(key)
    if why is not None:
        raise error(f"dataset key {key!r} {why}: keys become array names in the store",
                    file=file, key=None)
    return key  # type: ignore[return-value]


def numeric_dtype(text: str) -> np.dtype | None:
    """The numpy dtype `text` names when it is bool, integer or float; None otherwise."""
    try:
        dtype = np.dtype(text)
    except (TypeError, ValueError, SyntaxError):
        return None
    return dtype if dtype.kind in "biuf" else None


def lossy_cast(values: np.ndarray, dtype: np.dtype) -> str | None:
    """How casting `values` to `dtype` would change them, or None when it keeps them.

    Float to a narrower float is not lossy here (float64 joint angles are stored as float32 by
    default, losing only digits below the sensor's noise), unless a value overflows. Anything to
    an integer or bool type must keep every value exactly.
    """
    dtype = np.dtype(dtype)
    src = np.asarray(values)
    if src.dtype == dtype or src.size == 0:
        return None
    with np.errstate(all="ignore"):
        cast = src.astype(dtype)
        if dtype.kind == "f":
            bad = np.isfinite(src) & ~np.isfinite(cast) if src.dtype.kind == "f" \
                else ~np.isfinite(cast)
        else:
            back = cast.astype(src.dtype) if src.dtype.kind != "b" else cast.astype(bool)
            bad = back != src
    if not bad.any():
        return None
    i = np.unravel_index(int(np.argmax(bad)), bad.shape)
    return (f"{src.dtype} value {src[i].item()!r} becomes {cast[i].item()!r} as {dtype} "
            f"({int(bad.sum())} of {bad.size} values change)")



def physical_memory() -> int | None:
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):  # not on this platform
        return None


def human_bytes(n: float) -> str:
    for unit in ("B", "KB", "MB", "GB", "TB", "PB"):
        if n < 1024 or unit == "PB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} PB"


def check_memory(nbytes: float, doing: str, *, file: str | None = None,
                 key: str | None = None, hint: str = "") -> None:
    """Refuse, before allocating, what would not fit in 80 % of this machine's memory."""
    total = physical_memory()
    if total is not None and nbytes > 0.8 * total:
        raise SefaInputError(f"{doing} needs about {human_bytes(nbytes)}, more than this "
                             f"machine's {human_bytes(total)} of memory{hint}", file=file,
                             key=key)
