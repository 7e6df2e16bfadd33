"""Terminal output: rich tables and spinners on a terminal, plain line logs elsewhere."""

from __future__ import annotations

import contextlib
import sys
from pathlib import Path

from rich.console import Console
from rich.table import Table

from sefa_model.progress import RateMeter


console = Console(stderr=True)
# Tables stay readable when piped to a file or a CI log, where rich would assume 80 columns.
out = Console() if sys.stdout.isatty() else Console(width=140)


class Interrupted(Exception):
    """A Ctrl-C carried past typer, which turns every KeyboardInterrupt into exit code 130 and
    drops it, so that `sefa_cli.main.main` can print what the interrupt knows (an ingest's committed
    append, whether a conversion was published). Here, not in cli/main.py, so that the commands
    registered from other modules raise the class `main` catches (under `python -m sefa_cli.main`
    that module is `__main__`, and `sefa_cli.main` imported again would be another class)."""

    def __init__(self, e: KeyboardInterrupt):
        super().__init__(str(e))
        self.interrupt = e


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
    flat = _flat(values)
    text = " ".join(f"{x:.4g}" if isinstance(x, float) else str(x) for x in flat[:limit])
    return text + (f" ... ({len(flat)})" if len(flat) > limit else "")


def render_store_heading(s: dict) -> None:
    """A store in one line: where, its rate, episodes and frames."""
    out.print(f"[bold]{s['path']}[/]  sefa_format {s['sefa_format']}, {s['fps']:g} fps, "
              f"{s['n_episodes']} episodes, {s['n_frames']} frames, episode length "
              f"{s['episode_length'].get('min')}..{s['episode_length'].get('max')} "
              f"(mean {s['episode_length'].get('mean', 0):.1f})")


def render_store(s: dict) -> None:
    render_store_heading(s)
    t = Table(title="keys")
    for col in ("key", "type", "shape", "dtype", "constant dims"):
        t.add_column(col, no_wrap=col == "key")
    for key, f in s["features"].items():
        t.add_row(key, f["type"], str(tuple(f["shape"])), f["dtype"],
                  _fmt(_constant_dims(f.get("stats"))) or "-")
    out.print(t)
    stats = dimension_table(s["features"])
    if stats.row_count:
        out.print(stats)
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


STATS = ("min", "max", "mean", "std")
MAX_DIMS_SHOWN = 16  # per key; `sefa inspect --json` has every dimension


def dimension_table(features: dict) -> Table:
    """Statistics one row per dimension (a row of numbers per statistic wrapped into an
    unreadable column): the low-dim keys, a long key cut at MAX_DIMS_SHOWN rows."""
    t = Table(title="per-dimension statistics")
    for col in ("key", "dim", *STATS, "q01", "q99"):
        t.add_column(col, no_wrap=True, justify="left" if col == "key" else "right")
    for key, f in features.items():
        st = f.get("stats") or {}
        if f["type"] == "image" or not st.get("mean"):
            continue
        columns = {name: _flat(st.get(name, [])) for name in (*STATS, "q01", "q99")}
        n = len(columns["mean"])
        for d in range(min(n, MAX_DIMS_SHOWN)):
            t.add_row(key if d == 0 else "", str(d),
                      *(_num(float(v[d])) if d < len(v) else "-" for v in columns.values()))
        if n > MAX_DIMS_SHOWN:
            t.add_row("", f"+{n - MAX_DIMS_SHOWN}", *["(--json)"] + [""] * 5)
    return t


def _flat(values) -> list:
    flat: list = []

    def walk(v):
        if isinstance(v, list):
            for x in v:
                walk(x)
        else:
            flat.append(v)
    walk(values)
    return flat


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


def format_duration(seconds: float) -> str:
    seconds = int(round(seconds))
    h, rest = divmod(seconds, 3600)
    m, s = divmod(rest, 60)
    return f"{h}:{m:02d}:{s:02d}" if h else f"{m}:{s:02d}"


def _field(key: str, value) -> str:
    if isinstance(value, float):
        return f"{key.replace('_', ' ')} " + ("-" if value != value else f"{value:.4g}")
    return f"{key.replace('_', ' ')} {value}"


def progress_line(task: str, done: int, total: int, fields: dict, meter: RateMeter, now: float,
                  unit: str = "it") -> str:
    """`train 40/400 (10%) loss 0.95 | 7.3 step/s | elapsed 0:05 | ETA 0:49`: the rate and
    the ETA measured past the run's warm-up, over its last minute (sefa_model/progress.py)."""
    parts = [f"{task} {done}/{total} ({done / max(total, 1):.0%})"]
    parts += [_field(k, v) for k, v in fields.items()]
    text = " ".join(parts)
    rate = meter.rate()
    if rate is not None:
        text += f" | {rate:.3g} {unit}/s" if rate >= 1 else f" | {1 / rate:.3g} s/{unit}"
    text += f" | elapsed {format_duration(now - meter.start[0])}"
    eta = meter.eta()
    if eta is not None and done < total:
        text += f" | ETA {format_duration(eta)}"
    return text


UNITS = {"train": "step", "features": "window", "couplings": "window", "rollouts": "episode",
         "align": "pair", "offline eval": "NFE", "convert": "episode"}


class TrainProgress:
    """Every long task's progress (training steps, coupling windows, rollouts, ...): rich bars
    with rate and ETA on a terminal; elsewhere a plain line with the same numbers every 5 % or
    every `interval` seconds, whichever comes first."""

    def __init__(self, enabled: bool = True, interval: float = 30.0):
        import time

        self.enabled = enabled
        self.tty = sys.stderr.isatty()
        self.interval = interval
        self._now = time.monotonic
        self._bar = None
        self._tasks: dict[str, int] = {}
        self._meters: dict[str, RateMeter] = {}
        self._last: dict[str, tuple[int, float]] = {}
        self._listening = None
        self._loss: tuple[float, int] | None = None  # the last training loss and its step

    def __enter__(self) -> "TrainProgress":
        from sefa_model.progress import listening

        if self.enabled and self.tty:
            from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn,
                                       TimeElapsedColumn)

            self._bar = Progress(TextColumn("{task.description}"), BarColumn(),
                                 MofNCompleteColumn(), TextColumn("{task.fields[info]}"),
                                 TimeElapsedColumn(), TextColumn("ETA {task.fields[eta]}"),
                                 console=console, refresh_per_second=2)
            self._bar.__enter__()
        self._listening = listening(self.update)
        self._listening.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        self._listening.__exit__(*exc)
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
        """Training reads its loss only at log steps (a host sync), so between them the same
        value comes again: it is shown with the step it was measured at."""
        seen = self._loss
        same = seen is not None and step >= seen[1] and (
            loss == seen[0] or (loss != loss and seen[0] != seen[0]))  # NaN: none measured yet
        if not same:  # a new value, or a new training
            seen = self._loss = (loss, step)
        fresh = seen[1] == step or loss != loss
        self.update("train", step, total,
                    {"loss": loss} if fresh else {"loss": f"{loss:.4g} (at step {seen[1]})"})

    def update(self, task: str, done: int, total: int, fields: dict) -> None:
        if not self.enabled:
            return
        now = self._now()
        meter = self._meters.get(task)
        last = self._last.get(task)  # (pct, time, done) of the last plain line
        if meter is None or (last is not None and done < last[2]) or meter.total != total:
            # a new run of the task (the next training, the next checkpoint's rollouts); a
            # task's first report comes after its first unit (a training's step 1)
            meter = self._meters[task] = RateMeter(max(done - 1, 0), now, total)
            last = None
            if self._bar is not None and task in self._tasks:
                self._bar.remove_task(self._tasks.pop(task))
        meter.add(done, now)
        unit = UNITS.get(task, "it")
        if self._bar is not None:
            info = " ".join(_field(k, v) for k, v in fields.items())
            rate = meter.rate()
            if rate is not None:
                info += f" {rate:.3g} {unit}/s" if rate >= 1 else f" {1 / rate:.3g} s/{unit}"
            # our meter's ETA, past the warm-up: rich's own needs several updates within 30 s,
            # and shows -:--:-- for slow blocks
            eta = meter.eta()
            eta = format_duration(eta) if eta is not None else "-"
            if task not in self._tasks:
                self._tasks[task] = self._bar.add_task(task, total=total, completed=done,
                                                       info=info, eta=eta)
            self._bar.update(self._tasks[task], completed=done, total=total, info=info, eta=eta)
            self._last[task] = (0, now, done)
            return
        pct = done * 20 // max(total, 1)  # every 5 %
        if last is None or pct != last[0] or now - last[1] >= self.interval or done == total:
            self._last[task] = (pct, now, done)
            print(progress_line(task, done, total, fields, meter, now, unit), file=sys.stderr,
                  flush=True)
        else:
            self._last[task] = (last[0], last[1], done)

    def callbacks(self):
        from sefa_model.train.loop import Callbacks

        return Callbacks(log=self.log, on_step=self.on_step)


def render_policy(s: dict) -> None:
    """`sefa demo`'s table: each policy under each execution, in the simulator and on the
    validation windows, then what it shows in words."""
    n = s["rows"][0]["n_test"] if s["rows"] else 0
    t = Table(title=f"{s['env']}: success on {n} test seeds (± its standard error), action MSE on "
                    f"{s['val_windows']} validation windows")
    for col in ("policy", "execution", "success", "NFE", "ms a prediction (batch 1)",
                "val action MSE"):
        t.add_column(col, justify="left" if col in ("policy", "execution") else "right")
    for r in s["rows"]:
        p, every = r["success_rate"], r["every"]
        execution = "a prediction every step" if every == 1 else f"{every} actions a prediction"
        t.add_row(r["policy"], execution,
                  f"{p:.0%} ± {100 * (p * (1 - p) / r['n_test']) ** 0.5:.0f}%", str(r["nfe"]),
                  f"{r['latency_ms']:.3g}", f"{r['val_action_mse']:.4g}")
    t.add_row("mean action (baseline)", "-", "-", "-", "-", f"{s['mean_action_mse']:.4g}")
    out.print(t)
    for line in s.get("findings", []):
        out.print(line, highlight=False, markup=False)


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


def render_lerobot(s: dict) -> None:
    length = s.get("episode_length") or {}
    out.print(f"[bold]{s['path']}[/]  LeRobot {s['codebase_version']}, {s['fps']:g} fps, "
              f"{s['n_episodes']} episodes, {s['n_frames']} frames, episode length "
              f"{length.get('min')}..{length.get('max')}"
              + (f", robot {s['robot_type']}" if s.get("robot_type") else ""), highlight=False)
    t = Table(title="features")
    for col in ("feature", "dtype", "shape", "codec", "ingest reads it"):
        t.add_column(col, no_wrap=col == "feature")
    for name, f in s["features"].items():
        t.add_row(name, str(f["dtype"]), str(f["shape"]), f.get("codec") or "-",
                  "yes" if f["read"] else f"no ({s['skipped'].get(name, '')})")
    out.print(t)
    stats = dimension_table({k: {"type": "image" if f["dtype"] in ("video", "image") else "low_dim",
                                 "stats": f.get("stats")} for k, f in s["features"].items()})
    if stats.row_count:
        stats.title += f" (the dataset's: {s['stats_source']})"
        out.print(stats)
    out.print("tasks: " + "; ".join(s["tasks"][:5]) + (f" ... ({len(s['tasks'])})"
                                                       if len(s["tasks"]) > 5 else ""),
              highlight=False, markup=False)


def _constant_dims(stats):
    # imported here: sefa_data.store.inspect pulls in zarr (about 2 s), which `sefa status` and
    # `sefa --help` never need
    from sefa_data.store.inspect import constant_dims

    return constant_dims(stats)


def render_presets(rows: list[dict]) -> None:
    """`sefa presets`: a name, what it is for, and the commands that take it with their files."""
    t = Table(title="presets (sefa train --preset NAME, sefa run --preset NAME)")
    for col in ("name", "for", "sefa run", "sefa train"):
        t.add_column(col, no_wrap=col == "name")
    for r in rows:
        t.add_row(r["name"], r["for"] or "-", Path(r["run"]).name if r["run"] else "-",
                  Path(r["train"]).name if r["train"] else "-")
    out.print(t)
    folder = next((Path(r["run"] or r["train"]).parent for r in rows), None)
    if folder is not None:
        out.print(f"files in {folder}", highlight=False, markup=False)
