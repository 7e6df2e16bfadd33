"""`sefa bench`: measurements on this machine, printed as tables or JSON.

Each command parses its options, calls one library function and prints what it returns; the
measuring code lives in the library. Every report starts with the machine it was measured on,
since the numbers only compare within one machine. Commands follow one another below, each
with its own renderers after it.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.table import Table

from sefa_cli.console import Reporter, out
from sefa_data.errors import SefaInputError

bench_app = typer.Typer(add_completion=False, no_args_is_help=True)

JsonFlag = Annotated[bool, typer.Option("--json", help="Print the results as JSON on stdout.")]


@bench_app.callback()
def bench() -> None:
    """Measure sefa's speed on this machine (no numbers are asserted)."""
    # A callback keeps `bench` a group even with a single command, so that `bench data` parses
    # the same way whether the sub-app is invoked alone or from `sefa`.


def _render_machine(machine: dict) -> None:
    from sefa_data.bench.throughput import machine_summary

    out.print(f"[bold]machine[/]: {machine_summary(machine)}; {machine['platform']}",
              highlight=False)


# ---- sefa bench data

@bench_app.command()
def data(
    data_dir: Annotated[Optional[Path], typer.Option("--data", help="The folder of real recordings (default: ../shared/data next to the repository).")] = None,
    repeat: Annotated[int, typer.Option(help="Runs per ingest measurement; the median is reported.")] = 3,
    only: Annotated[list[str], typer.Option("--only", help="Only this recording: kuka_ros1, kuka_mcap, pusht, or images (Push-T frames written as camera bags; see --image-frames) (repeatable; default all). The sampler is measured with pusht.")] = [],
    seconds: Annotated[float, typer.Option(help="Seconds per sampler measurement.")] = 3.0,
    image_frames: Annotated[int, typer.Option(help="images: at least this many Push-T frames in each camera bag.")] = 5000,
    as_json: JsonFlag = False,
) -> None:
    """Ingest throughput against the reader library's raw rate, image ingest against decoding
    alone, and sampler windows/s."""
    from sefa_data.errors import SefaInputError
    from sefa_data.bench.throughput import (DEFAULT_DATA_DIR, RECORDING_NAMES, image_ingest_throughput,
                                      ingest_throughput, machine_description, sampler_throughput)

    data_dir = data_dir or DEFAULT_DATA_DIR
    rep = Reporter(quiet=as_json)
    names = (*RECORDING_NAMES, "images")
    unknown = [name for name in only if name not in names]
    if unknown:
        raise SefaInputError(f"unknown recording '{unknown[0]}' (available: {', '.join(names)})",
                             key="--only")
    recordings = [name for name in only if name != "images"]
    ingest = images = sampler = None
    if not only or recordings:
        with rep.status(f"ingest throughput, median of {repeat}"):
            ingest = ingest_throughput(data_dir, repeat=repeat, only=recordings or None,
                                       log=rep.line)
    if not only or "images" in only:
        with rep.status(f"image ingest throughput, median of {repeat}"):
            images = image_ingest_throughput(data_dir, frames=image_frames, repeat=repeat,
                                             log=rep.line)
    if not only or "pusht" in only:  # the sampler's windows come from Push-T
        with rep.status(f"sampler throughput, {seconds:g} s per measurement"):
            sampler = sampler_throughput(None, data_dir=data_dir, seconds=seconds, log=rep.line)
    result = {"machine": machine_description(), "ingest": ingest, "images": images,
              "sampler": sampler}
    if as_json:
        print(json.dumps(result, indent=2))
        return
    _render_machine(result["machine"])
    if ingest is not None:
        _render_ingest(ingest)
    if images is not None:
        _render_images(images)
    if sampler is not None:
        _render_sampler(sampler)


def _render_ingest(r: dict) -> None:
    t = Table(title=f"ingest throughput against the raw reader, messages/s (median of {r['repeat']})")
    for col in ("recording", "messages", "raw reader", "ours to RAM", "ratio", "ours to disk", "ratio"):
        t.add_column(col, justify="left" if col == "recording" else "right")
    for row in r["rows"]:
        t.add_row(row["input"], str(row["messages"]), f"{row['raw_msgs_per_s']:,.0f}",
                  f"{row['ours_ram_msgs_per_s']:,.0f}", f"{row['ratio_ram']:.2f}",
                  f"{row['ours_disk_msgs_per_s']:,.0f}", f"{row['ratio_disk']:.2f}")
    out.print(t)
    low = r["lowest_ratio"]
    out.print(f"lowest ratio (ours / raw): {low['ram']:.2f} in RAM ({r['ram_dir']}), "
              f"{low['disk']:.2f} on disk ({r['disk_dir']}); goal >= {r['goal']:.2f}",
              highlight=False)


def _render_images(r: dict) -> None:
    workers = r["decode_workers"]
    t = Table(title=f"image ingest against decoding alone, frames/s ({r['frames']} Push-T frames "
                    f"as camera bags, JPEG quality {r['jpeg_quality']}; median of {r['repeat']})")
    for col in ("recording", "size", "decoding", "ingest", "ratio",
                f"{workers} worker{'' if workers == 1 else 's'}", "ratio",
                "pixel error max / mean"):
        t.add_column(col, justify="left" if col == "recording" else "right")
    for row in r["rows"]:
        h, w = row["image_size"]
        pool = ([f"{row['workers_fps']:,.0f}", f"{row['workers_ratio']:.2f}"]
                if row["workers_fps"] else ["-", "-"])
        err = row["pixel_error"]
        t.add_row(row["input"], f"{h}x{w}", f"{row['decode_fps']:,.0f}",
                  f"{row['reader_fps']:,.0f}", f"{row['reader_ratio']:.2f}", *pool,
                  f"{err['max']} / {err['mean']:.2f}")
    out.print(t)
    low = r["lowest_ratio"]
    pool = "" if low["workers"] is None else f", {low['workers']:.2f} with decode workers"
    out.print(f"lowest ratio (ingest / decoding): {low['reader']:.2f} with the reader decoding"
              f"{pool}; goal >= {r['goal']:.2f}", highlight=False)


def _render_sampler(r: dict) -> None:
    t = Table(title=f"sampler throughput on Push-T, windows/s ({r['windows']} training windows, "
                    f"horizon {r['horizon']}, n_obs_steps {r['n_obs_steps']}, "
                    f"n_action_steps {r['n_action_steps']}, batch {r['batch']})")
    t.add_column("windows")
    t.add_column("windows/s", justify="right")
    for row in r["rows"]:
        t.add_row(" ".join(row["label"].split()), f"{row['windows_per_s']:,.0f}")
    out.print(t)
    ratio = r["batch_over_window"]
    images = "" if ratio["images"] is None else f", images {ratio['images']:.1f}x"
    out.print(f"batch() / window(): low-dim {ratio['low_dim']:.0f}x{images}", highlight=False)
    if r["image_cache"] is not None:
        c = r["image_cache"]
        out.print(f"image cache: {c['frames']} frames held, hit rate {c['hit_rate']:.0%}",
                  highlight=False)


# ---- sefa bench latency

@bench_app.command()
def latency(
    targets: Annotated[list[str], typer.Argument(help="Checkpoints or run dirs (a relative one looked for in the workspace first), each optionally @SOLVER[-STEPS]: train@rk45 train@euler-1 ddpm@ddim-10 (none: the checkpoint's own setting).")],
    store: Annotated[Optional[Path], typer.Option(help="Store whose validation window is the observation (default: WORKSPACE/dataset.zarr when it exists).")] = None,
    device: Annotated[str, typer.Option(help="auto, cpu, cuda, cuda:N or mps.")] = "auto",
    compile: Annotated[bool, typer.Option("--compile", help="torch.compile encoder + fixed-step sampler (CUDA graphs on a GPU).")] = False,
    calls: Annotated[int, typer.Option(help="Timed calls per setting (fewer for slow settings, see --max-seconds).")] = 200,
    warmup: Annotated[int, typer.Option(help="Untimed calls first.")] = 20,
    max_seconds: Annotated[float, typer.Option(help="Stop timing a setting after this long (at least 20 calls).")] = 20.0,
    passes: Annotated[int, typer.Option(help="Time every target this many times in turn and keep each one's fastest pass (a shared machine).")] = 1,
    threads: Annotated[Optional[int], typer.Option("--threads", min=1, help="CPU threads for torch (default: `threads` in the workspace's sefa.yaml, else torch's own choice); the report records them.")] = None,
    samples: Annotated[Optional[str], typer.Option("--samples", help="Also time one decision drawing N chunks for one observation in one batched call, for each N of this comma-separated list (e.g. 1,4,16,64), and each execution's cost per control step.")] = None,
    fps: Annotated[Optional[float], typer.Option(help="The robot's control rate, Hz: each execution's cost per step is checked against its period (default: the store's rate).")] = None,
    workspace: Annotated[Path, typer.Option("--workspace", "-w", help="Workspace directory.")] = Path("."),
    as_json: JsonFlag = False,
) -> None:
    """Batch-1 predict_action latency per checkpoint and solver setting, next to a bare forward pass.

    Prints p50/p90/p99, NFE, the encoder's and one head evaluation's time, and the floor: one
    forward pass of the same network; then, at the control rate (--fps, else the store's),
    each execution's cost per step and whether it fits the period.

    Example: sefa bench latency train@rk45 distill --fps 30 --threads 1 -w ws"""
    from sefa_cli.params import set_threads  # the one reading of --threads and sefa.yaml's threads
    from sefa_model.eval.latency import bench_latency

    sizes = _sample_sizes(samples)
    if fps is not None and not (fps > 0 and fps != float("inf")):
        raise SefaInputError(f"{fps} is not a finite rate > 0", key="--fps")
    set_threads(threads, workspace)
    targets = [_in_workspace(workspace, t) for t in targets]
    if store is None and (workspace / "dataset.zarr").exists():
        store = workspace / "dataset.zarr"
    rep = Reporter(quiet=as_json)
    result = bench_latency(targets, store=store, device=device, calls=calls, warmup=warmup,
                           max_seconds=max_seconds, passes=passes, log=rep.line, compile=compile,
                           sample_sizes=sizes, fps=fps)
    if as_json:
        print(json.dumps(result, indent=2))
        return
    _render_machine(result["machine"])
    _render_latency(result)
    if sizes:
        _render_decisions(result)
    _render_executions(result)


def _in_workspace(workspace: Path, target: str) -> str:
    """A target's checkpoint looked for in the workspace first, as `sefa eval` and `sefa
    export` look (`train@rk45 -w ws` is ws/train at RK45); its setting kept."""
    from sefa_cli.paths import in_workspace

    path, at, setting = target.partition("@")
    return str(in_workspace(workspace, Path(path))) + at + setting


def _sample_sizes(text: str | None) -> tuple[int, ...]:
    if text is None:
        return ()
    parts = [p.strip() for p in text.split(",")]
    if not all(p.isdigit() and 1 <= int(p) <= 4096 for p in parts):
        raise SefaInputError(f"'{text}' is not a comma-separated list of sample counts in "
                             "1..4096 (e.g. 1,4,16,64)", key="--samples")
    return tuple(sorted({int(p) for p in parts}))


def _render_decisions(r: dict) -> None:
    t = Table(title="one decision: N chunks for one observation in one batched call, ms")
    for col in ("target", "kind", "setting", "N", "p50", "p90", "p99", "calls"):
        t.add_column(col, justify="left" if col in ("target", "kind", "setting") else "right")
    for row in r["decisions"]:
        t.add_row(row["target"], row["kind"], row["setting"], str(row["samples"]),
                  f"{row['p50_ms']:.3g}", f"{row['p90_ms']:.3g}", f"{row['p99_ms']:.3g}",
                  str(row["calls"]))
    out.print(t)


def _render_executions(r: dict) -> None:
    from sefa_model.eval.latency import fit_summary

    rate = "" if r["fps"] is None else f" at {r['fps']:g} Hz (period {1000 / r['fps']:.3g} ms)"
    t = Table(title=f"each execution per control step{rate}, ms")
    for col in ("target", "execution", "mean / step", "worst step (p99)", "fits the period"):
        t.add_column(col, justify="left" if col in ("target", "execution") else "right")
    for row in r["executions"]:
        fits = "-" if row["fits"] is None else ("yes" if row["fits"] else "no")
        t.add_row(row["target"], row["execution"], f"{row['mean_step_ms']:.3g}",
                  f"{row['worst_step_ms']:.3g}", fits)
    out.print(t)
    for line in fit_summary(r["executions"], r["fps"]) or [
            "no control rate known: --fps F says which executions fit F Hz"]:
        out.print(line, highlight=False, markup=False)


def _render_latency(r: dict) -> None:
    t = Table(title=f"batch-1 latency on {r['device']}"
                    + (f", {r['threads']} threads" if r['device'] == "cpu" else "")
                    + f", ms (after {r['warmup']} warm-up calls)")
    for col in ("target", "kind", "setting", "NFE", "p50", "p90", "p99", "encoder", "head",
                "bare forward", "p50 / forward", "calls"):
        t.add_column(col, justify="left" if col in ("target", "kind", "setting") else "right")
    for row in r["rows"]:
        t.add_row(row["target"], row["kind"], row["setting"], str(row["nfe"]),
                  f"{row['p50_ms']:.3g}", f"{row['p90_ms']:.3g}", f"{row['p99_ms']:.3g}",
                  f"{row['encoder_ms']:.3g}", f"{row['head_ms']:.3g}", f"{row['forward_ms']:.3g}",
                  f"{row['ratio_to_forward']:.2f}x", str(row["calls"]))
    out.print(t)
    if r["rows"]:
        out.print(f"observation: {r['rows'][0]['obs_source']}", highlight=False)
