"""Terminal output: rich tables and spinners on a terminal, plain line logs elsewhere."""

from __future__ import annotations

import contextlib
import sys

from rich.console import Console
from rich.table import Table

from sefa_data.inspect import constant_dims

console = Console(stderr=True)
# Tables stay readable when piped to a file or a CI log, where rich would assume 80 columns.
out = Console() if sys.stdout.isatty() else Console(width=140)


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
        t.add_column(col, no_wrap=col == "key")
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
    integrity = s.get("integrity") or {}
    if integrity.get("checksums"):
        scope = "every file" if integrity["level"] == "full" else "all but the image chunks"
        out.print(f"integrity: {integrity['files']} files present with their recorded sizes; "
                  f"checksums of {scope} match ({integrity['files_hashed']} hashed)")
    elif integrity:
        out.print("integrity: episode index and attributes consistent; no checksums recorded "
                  "(a store written before sefa recorded them)")


def _num(v, digits: int = 4) -> str:
    return "-" if v is None else f"{v:.{digits}g}" if isinstance(v, float) else str(v)


def render_recording(s: dict) -> None:
    out.print(f"[bold]{s['path']}[/]  {s.get('format', '')}, {s.get('message_count')} messages, "
              f"{_num(s.get('duration_s'))} s")
    t = Table(title="topics")
    for col in ("topic", "type", "count", "rate Hz", "max gap s", "header-log skew s (median)",
                "max |skew| s"):
        t.add_column(col, no_wrap=col == "topic")
    for name, info in s.get("topics", {}).items():
        t.add_row(name, str(info.get("type", "")).replace("/msg/", "/"), _num(info.get("count")),
                  _num(info.get("rate_hz")), _num(info.get("max_gap_s")),
                  _num(info.get("skew_median_s")), _num(info.get("skew_max_abs_s")))
    out.print(t)


class TrainProgress:
    """A rich progress bar with the loss on a terminal; a plain line every few percent elsewhere."""

    def __init__(self, enabled: bool = True):
        self.enabled = enabled
        self.tty = sys.stderr.isatty()
        self._bar = None
        self._task = None
        self._last_pct = -1

    def __enter__(self) -> "TrainProgress":
        if self.enabled and self.tty:
            from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn,
                                       TimeRemainingColumn)

            self._bar = Progress(TextColumn("train"), BarColumn(), MofNCompleteColumn(),
                                 TextColumn("loss {task.fields[loss]:.4f}"), TimeRemainingColumn(),
                                 console=console, refresh_per_second=2)
            self._bar.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        if self._bar is not None:
            self._bar.__exit__(*exc)

    def log(self, text: str) -> None:
        if not self.enabled:
            return
        if self._bar is not None:
            self._bar.console.print(text, highlight=False, markup=False)
        else:
            print(text, file=sys.stderr, flush=True)

    def on_step(self, step: int, total: int, loss: float) -> None:
        if not self.enabled:
            return
        if self._bar is not None:
            if self._task is None:
                self._task = self._bar.add_task("train", total=total, completed=step - 1, loss=loss)
            self._bar.update(self._task, completed=step, loss=loss)
            return
        pct = step * 20 // total  # every 5 %
        if pct != self._last_pct or step == total:
            self._last_pct = pct
            print(f"step {step}/{total} loss {loss:.4f}", file=sys.stderr, flush=True)

    def callbacks(self):
        from sefa_model.training import Callbacks

        return Callbacks(log=self.log, on_step=self.on_step)


def render_policy(s: dict) -> None:
    t = Table(title=f"policies on {s['val_windows']} validation windows of {s['checkpoint'].split('/train')[0]}")
    sim = any("success_rate" in r for r in s["rows"])
    cols = (["policy"] + (["Lift success"] if sim else []) +
            ["val action MSE", "NFE", "predict_action ms (batch 1)"])
    for col in cols:
        t.add_column(col)
    for r in s["rows"]:
        success = [f"{r['success_rate']:.0%} of {r['n_test']}"] if sim else []
        t.add_row(r["policy"], *success, f"{r['val_action_mse']:.4g}", str(r["nfe"]),
                  f"{r['latency_ms']:.2f}")
    t.add_row("mean action (baseline)", *(["-"] if sim else []), f"{s['mean_action_mse']:.4g}", "-", "-")
    out.print(t)


def render_hdf5(s: dict) -> None:
    length = s.get("demo_length") or {}
    out.print(f"[bold]{s['path']}[/]  hdf5 ({s['layout']} layout), {s['n_demos']} demos, "
              f"{s['steps']} steps, demo length {length.get('min')}..{length.get('max')}"
              + (f", env {s['env']}" if s.get("env") else ""))
    read_as = {path: key for key, path in s["reads"].items()}
    t = Table(title="datasets per demo")
    for col in ("path", "dtype", "frame shape", "demos", "ingest reads it as"):
        t.add_column(col, no_wrap=col == "path")
    for path, info in s["datasets"].items():
        t.add_row(path, info["dtype"], str(tuple(info["shape"])), str(info["demos"]),
                  read_as.get(path) or f"- ({info['why_not'] or 'not read'})")
    out.print(t)
    if s["masks"]:
        out.print("masks: " + ", ".join(f"{k} {v}" for k, v in s["masks"].items()))
    if s.get("problem"):
        out.print(f"[red]a plain `sefa ingest` of this file fails:[/] {s['problem']}",
                  highlight=False)
