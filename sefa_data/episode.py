"""The two in-memory shapes data takes between a reader and the store.

A reader of timestamped recordings (ROS bags, MCAP) yields one `Stream` per dataset key: the raw
samples with their own times. `time_align` turns streams into an `Episode`, whose arrays all share
one fixed-rate time axis. Readers of already fixed-rate formats (HDF5, Zarr) yield `Episode`s
directly.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Iterator

import numpy as np


@dataclass
class Stream:
    """Samples of one dataset key as recorded: ``values[i]`` was taken at ``times_ns[i]``."""

    key: str
    topic: str
    times_ns: np.ndarray  # (N,) int64, nanoseconds on the stamp source the map chose
    values: np.ndarray  # (N, *shape)
    names: list[str] | None = None  # one name per flattened value dimension, when known
    log_times_ns: np.ndarray | None = None  # (N,) recorder time, kept for the clock-skew check

    def __len__(self) -> int:
        return int(self.times_ns.shape[0])


@dataclass
class Episode:
    """One episode on a shared time axis: every array in ``data`` has the same length T."""

    data: dict[str, np.ndarray]
    source: str  # the input file (or file plus group) the episode came from
    start_time_ns: int = 0  # source time of frame 0; 0 when the format has no clock
    names: dict[str, list[str]] = field(default_factory=dict)  # per key, optional
    label: str = ""  # human name inside the source (demo_3, segment 2, ...)
    filters: set[str] = field(default_factory=set)  # robomimic-style filter keys it belongs to

    def __len__(self) -> int:
        return next(iter(self.data.values())).shape[0] if self.data else 0


@dataclass
class Recording:
    """What a reader returns for one input file: file-level metadata and its episodes.

    ``episodes`` is an iterator so that the store can write while the reader reads; a reader
    raises `SefaInputError` from inside it when it meets bad data, and the store rolls back.
    """

    meta: dict
    episodes: "Iterator[Episode]"
