"""The simulators' own data, no download: `sefa collect` (scripted expert demonstrations, headless)
and `sefa demo` (the built-in default: scripted Meta-World demos through every SeFA stage).
Registered on the main app by cli/main.py; the work is in sefa_sim and pipelines/builtin_demo.py."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Annotated

import typer

from sefa_cli.console import Interrupted, render_store_heading
from sefa_cli.params import JsonFlag, Threads, Workspace, set_threads
from sefa_data.errors import SefaInputError


def collect(
    out: Annotated[Path, typer.Argument(help="The HDF5 file to write (robomimic layout).")],
    env: Annotated[str, typer.Option(help="robosuite:Lift, or metaworld:TASK (one of Meta-World's 50 tasks: reach, pick-place, ...), each with its scripted expert.")] = "robosuite:Lift",
    episodes: Annotated[int, typer.Option(help="Episodes to attempt; only successful ones are kept.")] = 100,
    seed: Annotated[int, typer.Option(help="Episode i resets with seed + i (Meta-World: the seed fixes the object and goal positions).")] = 0,
    cameras: Annotated[bool, typer.Option(help="Also record agentview and eye-in-hand images (Lift only).")] = False,
    append: Annotated[bool, typer.Option("--append", help="OUT exists: add the new demonstrations after its own (same environment, seeds not already there).")] = False,
    force: Annotated[bool, typer.Option("--force", help="OUT exists: replace it (its demonstrations are lost).")] = False,
    as_json: JsonFlag = False,
) -> None:
    """Record scripted expert demonstrations headless (no download).

    A file that exists is never replaced silently: the command refuses unless given --append
    or --force, before it records anything.

    Example: sefa collect demos.hdf5 --env metaworld:reach --episodes 10"""
    from sefa_pipelines.evals import METAWORLD

    metaworld = env.startswith(METAWORLD)
    if not metaworld and env != "robosuite:Lift":
        raise SefaInputError(f"unknown environment '{env}' (available: robosuite:Lift, "
                             f"{METAWORLD}TASK)", key="--env")
    if metaworld and cameras:
        raise SefaInputError("--cameras records robosuite Lift's cameras; Meta-World "
                             "demonstrations are low-dim", key="--cameras")
    try:
        if metaworld:
            from sefa_sim.metaworld import collect_metaworld, resolve

            resolve(env.removeprefix(METAWORLD))  # a wrong name fails before the import below
            import metaworld as _  # noqa: F401  (not installed: the message below)
        else:
            from sefa_sim.collect import collect_lift
    except ImportError as e:
        raise SefaInputError(f"the simulator is not installed ({e}); install sefa[sim]") from None
    try:
        if metaworld:
            summary = collect_metaworld(out, env.removeprefix(METAWORLD), episodes, seed=seed,
                                        append=append, force=force)
            why = "info['success'] was never set within Meta-World's 500 steps"
        else:
            summary = collect_lift(out, episodes, seed=seed, cameras=cameras, append=append,
                                   force=force)
            why = "the cube was not lifted within the step limit"
    except KeyboardInterrupt as e:  # its line says what became of the file
        raise Interrupted(e) from None
    if as_json:
        print(json.dumps(summary, indent=2))
        return
    after = (f"; appended after its {summary['appended_to']}, it holds {summary['demos']}"
             if "appended_to" in summary else "")
    print(f"{out}: {summary['successful']}/{summary['attempted']} successful episodes kept "
          f"({summary['success_rate']:.0%}), {summary['steps']} steps{after}")
    if summary["failed_seeds"]:  # dropped demos are said, not only counted
        print(f"not kept ({why}): seeds {', '.join(map(str, summary['failed_seeds']))}",
              file=sys.stderr)


def demo(workspace: Workspace = Path("runs/demo"), threads: Threads = None,
         as_json: JsonFlag = False) -> None:
    """The built-in default, no downloads: scripted Meta-World demos through every SeFA stage.

    Records 10 scripted button-press demonstrations, ingests them, runs the pipeline, and
    compares the base flow (RK45 and one Euler step) with the one-step student, executing 8
    actions a prediction and predicting at every step. Run again, it answers from its cache."""
    from sefa_cli.console import TrainProgress, render_policy
    from sefa_pipelines.builtin_demo import run_demo

    set_threads(threads, workspace)
    try:
        import metaworld as _  # noqa: F401  (not installed: the message below)
    except ImportError as e:
        raise SefaInputError(f"the simulator is not installed ({e}); install sefa[sim]") from None
    with TrainProgress(enabled=not as_json) as progress:
        summary = run_demo(workspace, log=progress.log, on_step=progress.on_step)
    if as_json:
        print(json.dumps(summary, indent=2))
    else:
        # the store in one line (`sefa inspect` has its keys and statistics), then the result
        render_store_heading(summary["store"])
        render_policy(summary["policy"])
