"""What a workspace holds and how it is set: `sefa status` (every stage's state and the next
command) and `sefa config show|set|reset` (sefa.yaml, and the command-line settings kept on top
of it). They run no stage. Registered on the main app by
cli/main.py."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Annotated

import typer

from sefa_cli.params import JsonFlag, Workspace


def status(workspace: Workspace = Path("."), as_json: JsonFlag = False) -> None:
    """Every stage of the workspace (ingest, train, reflow, align, distill, eval): state, path,
    key metric, duration, and the next command.

    Example: sefa status -w ws"""
    from sefa_pipelines.overview import overview

    view = overview(workspace)
    if as_json:
        print(json.dumps(view, indent=2))
        return
    for note in view["notes"]:
        print(note)
    for r in view["rows"]:
        print(f"{r['stage']:14s} {r['state']:8s} {r['path'] or '-':34s} {r['metric'] or ''}"
              + (f" ({r['duration']})" if r.get("duration") else ""))
        if r["state"] not in ("cached", "done") and r.get("reason"):
            print(f"{'':24s}{r['reason']}")
    print(f"next: {view['next']}")


config_app = typer.Typer(help="The workspace's settings.", no_args_is_help=True,
                         context_settings={"help_option_names": ["-h", "--help"]})


@config_app.command("show")
def config_show(workspace: Workspace = Path("."), as_json: JsonFlag = False) -> None:
    """The resolved settings with every key: sefa.yaml, the command-line settings kept on top of
    it, the machine's defaults, and the full train config of each stage.

    Example: sefa config show -w ws"""
    import yaml

    from sefa_pipelines.overview import resolved_config

    data = resolved_config(workspace)
    if as_json:
        print(json.dumps(data, indent=2))
    else:
        sys.stdout.write(yaml.safe_dump(data, sort_keys=False))


# unknown options are values here: `sefa config set align.eps -1` (click would read -1 as an option)
@config_app.command("set", context_settings={"ignore_unknown_options": True})
def config_set(
    key: Annotated[str, typer.Argument(help="A dotted key of sefa.yaml (reflow.train_steps, distill.train_steps, distill.steps, align.eps, threads) or of the base policy's train config (train.training.max_steps).")],
    value: Annotated[str, typer.Argument(help="The value, as YAML (200, 0.05, null, [0,2]).")],
    workspace: Workspace = Path("."),
) -> None:
    """Set one setting in sefa.yaml, checked first (the old file kept as sefa.yaml.bak).

    Example: sefa config set reflow.train_steps 200 -w ws"""
    from sefa_pipelines.workspace import set_setting

    print(set_setting(workspace, key, value))


@config_app.command("reset")
def config_reset(workspace: Workspace = Path(".")) -> None:
    """Drop the command-line settings kept on top of sefa.yaml (`sefa train training.max_steps=20`
    keeps its setting for the next commands until --save or this); the runs made with them are
    kept.

    Example: sefa config reset -w ws"""
    from sefa_pipelines.workspace import reset_flags

    print(reset_flags(workspace))
