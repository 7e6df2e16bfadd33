"""Terminal output: rich tables and spinners on a terminal, plain line logs elsewhere."""

from __future__ import annotations

import contextlib
import sys

from rich.console import Console
from rich.table import Table

from sefa_data.inspect import constant_dims

console = Console(stderr=True)
out = Console()


class Reporter:
    """Progress lines on stderr; silent with `quiet` (when stdout carries JSON)."""

    def __init__(self, quiet: bool = False):
        self.quiet = quiet
        self.tty = sys.stderr.isatty()

    def line(self, text: str) -> None:
        if self.quiet:
            return
        if self.tty:
            console.print(text, highlight=False, markup=False)
        else:
            print(text, file=sys.stderr, flush=True)

    @contextlib.contextmanager
    def status(self, text: str):
        if self.tty and not self.quiet:
            with console.status(text):
                yield
        else:
            self.line(text)
            yield


def _fmt(values, limit: int = 6) -> str:
    flat = []

    def walk(v):
        if isinstance(v, list):
            for x in v:
                walk(x)
        else:
            flat.append(v)

    walk(values)
    text = " ".join(f"{x:.4g}" if isinstance(x, float) else str(x) for x in flat[:limit])
    return text + (f" ... ({len(flat)})" if len(flat) > limit else "")


def render_store(s: dict) -> None:
    out.print(f"[bold]{s['path']}[/]  sefa_format {s['sefa_format']}, {s['fps']:g} fps, "
              f"{s['n_episodes']} episodes, {s['n_frames']} frames, episode length "
              f"{s['episode_length'].get('min')}..{s['episode_length'].get('max')} "
              f"(mean {s['episode_length'].get('mean', 0):.1f})")
    t = Table(title="keys")
    for col in ("key", "type", "shape", "dtype", "min", "max", "mean", "std", "constant dims"):
        t.add_column(col)
    for key, f in s["features"].items():
        st = f.get("stats") or {}
        t.add_row(key, f["type"], str(tuple(f["shape"])), f["dtype"], _fmt(st.get("min", [])),
                  _fmt(st.get("max", [])), _fmt(st.get("mean", [])), _fmt(st.get("std", [])),
                  _fmt(constant_dims(st)) or "-")
    out.print(t)
    out.print("masks: " + ", ".join(f"{k} {v}" for k, v in s["masks"].items()))
    t = Table(title="sources")
    for col in ("path", "format", "sha256", "size", "episodes"):
        t.add_column(col)
    for src in s["sources"]:
        t.add_row(src["path"], src["format"], src["sha256"][:12], str(src["size"]),
                  f"{src['episodes'][0]}..{src['episodes'][0] + src['episodes'][1] - 1}")
    out.print(t)


def render_recording(s: dict) -> None:
    out.print(f"[bold]{s.get('path', '')}[/]  " + ", ".join(
        f"{k} {v}" for k, v in s.items() if k not in ("path", "topics") and not isinstance(v, (dict, list))))
    t = Table(title="topics")
    topics = s.get("topics", {})
    rows = topics.items() if isinstance(topics, dict) else ((x.get("topic"), x) for x in topics)
    cols = []
    for _, info in rows:
        cols = [c for c in info if c != "topic"]
        break
    t.add_column("topic")
    for c in cols:
        t.add_column(c)
    rows = topics.items() if isinstance(topics, dict) else ((x.get("topic"), x) for x in topics)
    for name, info in rows:
        t.add_row(str(name), *[_fmt(info.get(c)) if isinstance(info.get(c), (list, float))
                               else str(info.get(c)) for c in cols])
    out.print(t)
