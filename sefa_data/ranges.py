"""Valid ranges of numeric settings, declared beside the setting and checked before any work.

A config field states its range in its metadata (`knob(256, Range(lo=1, integer=True))`);
`config_io.from_dict` checks every such field of every config it builds, so a YAML file, a
`key=value` override and a dict built in code all meet the same check. Command-line options
that are not config keys check their values against a `Range` with the option's own name.

A range refuses NaN and infinities always: no knob in sefa means anything at either.
"""

from __future__ import annotations

import math
from dataclasses import MISSING, dataclass, field, fields
from typing import Any, Callable

from sefa_data.errors import ConfigError


@dataclass(frozen=True)
class Range:
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False  # lo itself excluded: a positive real is Range(lo=0, lo_open=True)
    hi_open: bool = False
    integer: bool = False

    def words(self) -> str:
        kind = "an integer" if self.integer else "a finite number"
        lo = None if self.lo is None else f"{'>' if self.lo_open else '>='} {_show(self.lo)}"
        hi = None if self.hi is None else f"{'<' if self.hi_open else '<='} {_show(self.hi)}"
        if lo and hi:
            return (f"{kind} in {'(' if self.lo_open else '['}{_show(self.lo)}, {_show(self.hi)}"
                    f"{')' if self.hi_open else ']'}")
        return " ".join(p for p in (kind, lo or hi) if p)

    def problem(self, value: Any) -> str | None:
        """What is wrong with `value`, or None when it is in range."""
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return f"expected a number, got {value!r}"
        if isinstance(value, float) and not math.isfinite(value):
            return f"{value} is not a finite number"
        if self.integer and not float(value).is_integer():
            return f"{value} is not an integer"
        if self.lo is not None and (value <= self.lo if self.lo_open else value < self.lo):
            return f"{_show(value)} is too small"
        if self.hi is not None and (value >= self.hi if self.hi_open else value > self.hi):
            return f"{_show(value)} is too large"
        return None

    def check(self, value: Any, key: str | None, file: str | None = None) -> None:
        """Raise a ConfigError naming `key` and the valid range; None (an unset optional) passes,
        a list is checked item by item."""
        if value is None:
            return
        items = enumerate(value) if isinstance(value, (list, tuple)) else [(None, value)]
        for i, item in items:
            wrong = self.problem(item)
            if wrong is not None:
                where = key if i is None or key is None else f"{key}[{i}]"
                raise ConfigError(f"{wrong} (valid: {self.words()})", file=file, key=where)


def _show(value: Any) -> str:
    if isinstance(value, int) or (isinstance(value, float) and value.is_integer() and abs(value) < 1e15):
        return str(int(value))
    return f"{value:g}"


# the common ones, by what they mean
def count(lo: int = 1, hi: int | None = None) -> Range:
    """An integer count or step number, lo..hi."""
    return Range(lo=lo, hi=hi, integer=True)


POSITIVE = Range(lo=0, lo_open=True)  # a finite real > 0
NONNEGATIVE = Range(lo=0)
UNIT_OPEN = Range(lo=0, hi=1, hi_open=True)  # [0, 1)
UNIT = Range(lo=0, hi=1)  # [0, 1]
SEED = count(0, 2 ** 32 - 1)  # numpy's seeds


def knob(default: Any = MISSING, valid: Range | None = None, *,
         factory: Callable[[], Any] | None = None) -> Any:
    """A dataclass field with its valid range (checked by `check_ranges`)."""
    meta = {"valid": valid} if valid is not None else {}
    if factory is not None:
        return field(default_factory=factory, metadata=meta)
    return field(default=default, metadata=meta)


def range_of(cls: type, name: str) -> Range | None:
    for f in fields(cls):
        if f.name == name:
            return f.metadata.get("valid")
    return None


def check_ranges(obj: Any, prefix: str = "", file: str | None = None) -> None:
    """Every field of dataclass `obj` that states a range, checked; the key is `prefix.field`."""
    for f in fields(obj):
        valid = f.metadata.get("valid")
        if valid is not None:
            valid.check(getattr(obj, f.name), f"{prefix}.{f.name}" if prefix else f.name, file)
