"""`sefa convert INPUT... --to lerobot --out DIR`: recordings or a store, as a LeRobot dataset.
Registered on the main app by cli/main.py; the work is in sefa_data.convert."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Optional

import typer

from cli.console import Interrupted, Reporter, TrainProgress
from sefa_data.errors import SefaInputError


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
    from sefa_data.convert import convert_to_lerobot

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
    if as_json:
        print(json.dumps(summary, indent=2))
