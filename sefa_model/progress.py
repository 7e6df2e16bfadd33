"""Progress of long work (training, coupling generation, alignment, evaluation), reported to
whoever listens: the CLI shows it as a progress bar on a terminal and as periodic plain lines
elsewhere. Library code only reports; with no listener a report costs a list lookup."""

from __future__ import annotations

from contextlib import contextmanager
from typing import Any, Callable, Iterator

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
