"""Recordings and stores: `sefa ingest` (and its --scaffold of a topic or key map), `sefa inspect`
and `sefa convert` (to a LeRobot dataset). Registered on the main app by cli/main.py; the work is
in sefa_data."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Annotated, Optional

import typer

from sefa_cli.console import Interrupted, Reporter, TrainProgress, render_recording, render_store
from sefa_cli.params import JsonFlag, Workspace
from sefa_data import atomic
from sefa_data.errors import SefaInputError

DEFAULT_STORE = "dataset.zarr"


def _pairs(items: list[str], what: str) -> dict[str, str]:
    out = {}
    for item in items:
        if "=" not in item:
            raise SefaInputError(f"{what} '{item}' is not of the form old=new")
        a, b = item.split("=", 1)
        out[a] = b
    return out


def ingest(
    inputs: Annotated[list[Path], typer.Argument(help="Recordings: .bag, .mcap, ROS 2 bag dirs, .hdf5, .zarr, .zarr.zip, LeRobot dataset folders (v3.0, v2.1)")],
    out: Annotated[Optional[Path], typer.Option("--out", "-o", help=f"Store to append to (default: WORKSPACE/{DEFAULT_STORE}).")] = None,
    topic_map: Annotated[Optional[Path], typer.Option("--map", "-m", help="Topic map YAML (ROS bags, MCAP), or HDF5 key map YAML (see --scaffold).")] = None,
    fps: Annotated[Optional[float], typer.Option(help="Frame rate of the store (required for a new store from Zarr input).")] = None,
    rename: Annotated[list[str], typer.Option(help="Zarr or LeRobot import: rename a key, old=new (repeatable).")] = [],
    key: Annotated[list[str], typer.Option(help="Zarr or LeRobot import: only this source key (repeatable; default all).")] = [],
    obs_key: Annotated[list[str], typer.Option(help="HDF5: observation keys to read (repeatable; default all).")] = [],
    action_key: Annotated[str, typer.Option(help="HDF5: the action dataset name.")] = "actions",
    filter_key: Annotated[Optional[str], typer.Option(help="HDF5: only demos in mask/<filter_key>.")] = None,
    hdf5_key: Annotated[list[str], typer.Option(help="HDF5: key map for other layouts, key=path/in/demo (repeatable).")] = [],
    skip_bad_demos: Annotated[bool, typer.Option(help="HDF5: skip a demo whose observation is missing or of another length than its actions (with a warning) instead of failing.")] = False,
    zarr_format: Annotated[int, typer.Option(help="Zarr format of a new store (2 or 3).")] = 2,
    scaffold: Annotated[bool, typer.Option(help="Write a starter map (a bag's topics, an HDF5 file's datasets) to --map or stdout and exit.")] = False,
    dry_run: Annotated[bool, typer.Option(help="Read and check everything; write nothing.")] = False,
    skip_failed: Annotated[bool, typer.Option(help="Go on past bad inputs and list them at the end.")] = False,
    decode_workers: Annotated[int, typer.Option(help="ROS inputs: processes that decode camera images beside the reader (0: the reader decodes them). Speed only: the store is the same. Helps only with idle cores; `python benchmarks/bench_image_ingest.py` measures it.")] = 0,
    allow_lossy_cast: Annotated[bool, typer.Option(help="LeRobot input: apply info.json's dtypes even where they change values (refused by default).")] = False,
    skip_stats_check: Annotated[bool, typer.Option(help="LeRobot input: do not compare the values read with the dataset's per-episode statistics (for stale statistics).")] = False,
    workspace: Workspace = Path("."),
    as_json: JsonFlag = False,
) -> None:
    """Append recordings to a Zarr episode store (Diffusion Policy layout)."""
    from sefa_data.readers.hdf5 import Hdf5Options
    from sefa_data.ingest import IngestOptions, ingest as run_ingest

    rep = Reporter(quiet=as_json)
    if scaffold:
        _write_scaffold(inputs, topic_map, fps, rep)
        return
    if zarr_format not in (2, 3):
        raise SefaInputError(f"--zarr-format must be 2 or 3, got {zarr_format}")
    options = IngestOptions(
        fps=fps, topic_map=str(topic_map) if topic_map else None,
        renames=_pairs(rename, "--rename"), keys=key or None,
        hdf5=Hdf5Options(obs_keys=obs_key or None, action_key=action_key, filter_key=filter_key,
                         key_map=_pairs(hdf5_key, "--hdf5-key"), skip_bad_demos=skip_bad_demos),
        zarr_format=zarr_format, skip_failed=skip_failed, dry_run=dry_run,
        decode_workers=decode_workers, allow_lossy_cast=allow_lossy_cast,
        skip_stats_check=skip_stats_check)
    store_path = out or workspace / DEFAULT_STORE
    try:
        with rep.status(f"ingesting {len(inputs)} input(s) into {store_path}"):
            report = run_ingest(inputs, store_path, options, log=rep.line)
    except KeyboardInterrupt as e:
        raise Interrupted(e) from None
    written = [r for r in report.inputs if r.status == "written"]
    if written and not dry_run:  # where it went: --out, or the workspace's default store
        rep.line(f"store: {store_path}: {sum(r.episodes for r in written)} episodes, "
                 f"{sum(r.frames for r in written)} frames appended")
    if report.failed:
        rep.line(f"{len(report.failed)} input(s) failed:")
        for r in report.failed:
            rep.line(f"  {r.message}")
    if as_json:
        from dataclasses import asdict

        print(json.dumps(asdict(report), indent=2))
    if report.failed:
        raise typer.Exit(1)


def _write_scaffold(inputs: list[Path], topic_map: Optional[Path], fps: Optional[float],
                    rep: Reporter) -> None:
    """--scaffold: one recording's starter map to --map's file, or to stdout; then its notes."""
    from sefa_data.ingest import scaffold_map

    if len(inputs) != 1:
        raise SefaInputError(f"--scaffold reads one recording, got {len(inputs)}")
    text, notes = scaffold_map(inputs[0], fps)
    if topic_map is None:
        sys.stdout.write(text)
    else:
        _write_new(topic_map, text)
        rep.line(f"wrote {topic_map}")
    for line in notes:
        rep.line(line)


def _write_new(path: Path, text: str) -> None:
    if path.is_dir():
        raise SefaInputError("is a directory; --map names the YAML file to write", file=str(path))
    atomic.write_text(path, text)


def inspect(
    path: Annotated[Optional[Path], typer.Argument(help="A sefa store, a bag/MCAP recording, an HDF5 file or a LeRobot dataset folder.")] = None,
    verify: Annotated[bool, typer.Option("--verify", help="Store: check every chunk's checksum, images included (a plain inspect checks presence and sizes, and the checksums of all but image chunks).")] = False,
    workspace: Workspace = Path("."),
    as_json: JsonFlag = False,
) -> None:
    """Show a store (episodes, keys, statistics, masks, provenance, integrity), a recording (topics, rates, gaps, skew), an HDF5 file (demos, keys, what ingest reads) or a LeRobot dataset (features, what ingest reads; exit 1 when files it references are missing)."""
    from sefa_data.ingest import detect_format

    path = path or workspace / DEFAULT_STORE
    fmt = detect_format(path)
    if verify and fmt != "zarr":
        raise SefaInputError("--verify checks a sefa store; this is a recording", file=str(path))
    if fmt == "zarr":
        from sefa_data.store.inspect import store_summary

        summary = store_summary(path, verify=verify)
        render = render_store
    elif fmt == "hdf5":
        from sefa_cli.console import render_hdf5
        from sefa_data.readers.hdf5 import inspect_hdf5

        summary = inspect_hdf5(path)
        render = render_hdf5
    elif fmt == "lerobot":
        from sefa_cli.console import render_lerobot
        from sefa_data.lerobot.reader import inspect_lerobot

        summary = inspect_lerobot(path)
        render = render_lerobot
    else:
        from sefa_data.readers.ros import inspect_recording

        summary = inspect_recording(path)
        render = render_recording
    if as_json:
        print(json.dumps(summary, indent=2))
    else:
        render(summary)
    if summary.get("problem"):  # what ingest would stop on (files missing, not fetched): exit 1
        if as_json:
            raise typer.Exit(1)
        raise SefaInputError(summary["problem"])


# LeRobot out
def convert(
    inputs: Annotated[list[Path], typer.Argument(help="Anything `sefa ingest` reads (bags, MCAP, HDF5, Zarr, LeRobot folders), or one sefa store.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="The dataset folder to create (must not exist).")],
    to: Annotated[str, typer.Option("--to", help="Output format: lerobot (LeRobot dataset v3.0, as LeRobot 0.6.1 writes it).")] = "lerobot",
    task: Annotated[list[str], typer.Option(help="Task string: once for every episode, or once per input in order (default: the tasks the input records).")] = [],
    codec: Annotated[str, typer.Option(help="Video codec: av1 (LeRobot's default, libsvtav1), h264 or hevc.")] = "av1",
    robot_type: Annotated[Optional[str], typer.Option(help="robot_type to record in info.json.")] = None,
    topic_map: Annotated[Optional[Path], typer.Option("--map", "-m", help="Topic map YAML (ROS bags, MCAP) or HDF5 key map, as for `sefa ingest`.")] = None,
    fps: Annotated[Optional[float], typer.Option(help="Frame rate, for inputs without a clock (Zarr).")] = None,
    rename: Annotated[list[str], typer.Option(help="Zarr or LeRobot import: rename a key, old=new (repeatable).")] = [],
    key: Annotated[list[str], typer.Option(help="Zarr or LeRobot import: only this source key (repeatable).")] = [],
    allow_lossy_cast: Annotated[bool, typer.Option(help="LeRobot input: apply info.json's dtypes even where they change values (refused by default).")] = False,
    skip_stats_check: Annotated[bool, typer.Option(help="LeRobot input: do not compare the values read with the dataset's per-episode statistics (for stale statistics).")] = False,
    encoder_timeout: Annotated[float, typer.Option(help="Seconds a video encoder may go without encoding a frame before it counts as stalled and the conversion stops (naming the episode).")] = 60.0,
    as_json: Annotated[bool, typer.Option("--json", help="Print a JSON summary on stdout.")] = False,
) -> None:
    """Convert recordings (or a sefa store) to a LeRobot v3.0 dataset that LeRobot itself loads."""
    from sefa_data.ingest import IngestOptions
    from sefa_data.convert import convert_to_lerobot, left_line

    if to != "lerobot":
        raise SefaInputError(f"unknown output format {to!r} (sefa converts to: lerobot)", key="--to")
    renames = {}
    for pair in rename:
        if "=" not in pair:
            raise SefaInputError(f"expected old=new, got {pair!r}", key="--rename")
        old, new = pair.split("=", 1)
        renames[old] = new
    options = IngestOptions(fps=fps, topic_map=str(topic_map) if topic_map else None,
                            renames=renames, keys=key or None,
                            allow_lossy_cast=allow_lossy_cast,
                            skip_stats_check=skip_stats_check)
    rep = Reporter(quiet=as_json)
    try:
        with TrainProgress(enabled=not as_json) as bar:
            summary = convert_to_lerobot(
                inputs, out, options, task, codec=codec, robot_type=robot_type, log=rep.line,
                progress=lambda done, total: bar.update("convert", done, total, {}),
                stall_timeout=encoder_timeout)
    except KeyboardInterrupt as e:  # its line says whether --out was written
        raise Interrupted(e) from None
    videos = (f"{len(summary['videos'])} video key(s) in {summary['codec']}" if summary["videos"]
              else "no video")
    rep.line(f"written: {out}: LeRobot v3.0, {summary['episodes']} episodes, "
             f"{summary['frames']} frames, {summary['tasks']} task(s), {videos}")
    if summary.get("left"):  # a temporary the file system would not remove: said last
        rep.line(f"note: {left_line(out, [Path(p) for p in summary['left']])}")
    if as_json:
        print(json.dumps(summary, indent=2))
