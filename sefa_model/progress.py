"""Progress of long work (training, coupling generation, alignment, evaluation), reported to
whoever listens: the CLI shows it as a progress bar on a terminal and as periodic plain lines
elsewhere. Library code only reports; with no listener a report costs a list lookup."""

from __future__ import annotations

import collections
import math
from contextlib import contextmanager
from typing import Any, Callable, Iterator, Sequence

Sink = Callable[[str, int, int, dict[str, Any]], None]
_sinks: list[Sink] = []


def report(task: str, done: int, total: int, **fields: Any) -> None:
    """`done` of `total` units of `task`; `fields` are running numbers worth showing (loss,
    mean score, NFE)."""
    for sink in _sinks:
        sink(task, done, total, fields)


@contextmanager
def listening(sink: Sink) -> Iterator[None]:
    _sinks.append(sink)
    try:
        yield
    finally:
        _sinks.remove(sink)


# ---- the measured rate of a running task, and its ETA
#
# The first units of a run pay one-time costs (allocation, lazy initialisation, cold caches), so
# a rate from them alone misleads (a demo's training measured 1.6 s a step over its steps 2-3,
# then ran at 0.35 s): its first 1 % of units (at least one, at most WARMUP_UNITS_MAX), or its
# first WARMUP_SECONDS if they pass sooner, are left out. On a shared machine the rate changes
# with the other jobs, so it is the rate of the last RATE_WINDOW seconds.
WARMUP_FRACTION = 0.01
WARMUP_UNITS_MAX = 50
WARMUP_SECONDS = 10.0
RATE_WINDOW = 60.0

Sample = tuple[float, float]  # (seconds, units done)


def warmup_units(units: int) -> int:
    """Units of a run of `units` left out of its rate, unless WARMUP_SECONDS pass first."""
    return min(max(1, math.ceil(WARMUP_FRACTION * units)), WARMUP_UNITS_MAX)


def warmed_up(start: Sample, now: Sample, total: int) -> bool:
    """Whether a run to `total` units that started at `start` (a resumed one mid-way) has
    finished its warm-up at `now`."""
    (t0, d0), (t, d) = start, now
    return d > d0 and (d - d0 >= warmup_units(int(total - d0)) or t - t0 >= WARMUP_SECONDS)


def window_rate(samples: Sequence[Sample], window: float = RATE_WINDOW
                ) -> tuple[float, float, float] | None:
    """(units per second, first unit, last unit) over the samples of the last `window` seconds
    (at least the last two), None when they span no time or no units."""
    if len(samples) < 2:
        return None
    t_last, d_last = samples[-1]
    i = next(i for i, (t, _) in enumerate(samples) if t >= t_last - window)
    t_first, d_first = samples[min(i, len(samples) - 2)]
    if t_last <= t_first or d_last <= d_first:
        return None
    return (d_last - d_first) / (t_last - t_first), d_first, d_last


def measured_rate(samples: Sequence[Sample], total: int, window: float = RATE_WINDOW
                  ) -> tuple[float, float, float] | None:
    """The rate of a run of `total` units from its samples (the first at its start, in time
    order): `window_rate` over the samples from the warm-up's end on; None until measured."""
    start = next((i for i, now in enumerate(samples) if warmed_up(samples[0], now, total)), None)
    return None if start is None else window_rate(samples[start:], window)


def eta_seconds(samples: Sequence[Sample], total: int, window: float = RATE_WINDOW
                ) -> float | None:
    """Seconds left of a run at its measured rate, None until it is measured."""
    measured = measured_rate(samples, total, window)
    return None if measured is None else max(0.0, total - samples[-1][1]) / measured[0]


class RateMeter:
    """`measured_rate` of one run as it goes, keeping only the samples it needs: the start, and
    from the warm-up's end on, the last window's."""

    def __init__(self, done: float, now: float, total: int, window: float = RATE_WINDOW):
        self.start: Sample = (now, done)
        self.total, self.window = total, window
        self.measuring: collections.deque[Sample] | None = None  # from the warm-up's end

    def add(self, done: float, now: float) -> None:
        if self.measuring is None:
            if warmed_up(self.start, (now, done), self.total):
                self.measuring = collections.deque([(now, done)])
            return
        self.measuring.append((now, done))
        while len(self.measuring) > 2 and self.measuring[1][0] < now - self.window:
            self.measuring.popleft()  # the window starts at or after the next one

    def measured(self) -> tuple[float, float, float] | None:
        return None if self.measuring is None else window_rate(self.measuring, self.window)

    def rate(self) -> float | None:
        measured = self.measured()
        return None if measured is None else measured[0]

    def eta(self) -> float | None:
        rate = self.rate()
        return None if rate is None else max(0.0, self.total - self.measuring[-1][1]) / rate
