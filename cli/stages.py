"""The commands that run the workspace's stages through the cached runner: `sefa train`, `reflow`,
`align`, `distill` and `run` (each builds its own stages and the upstream ones they read, as
pipelines/stages.py's graph says), and `sefa presets`, the settings `--preset NAME` names.
Registered on the main app by cli/main.py."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Annotated, Optional

import typer

from sefa_cli.console import Interrupted
from sefa_cli.params import Device, JsonFlag, Threads, Workspace, start_process
from sefa_data.errors import SefaInputError

Yes = Annotated[bool, typer.Option("--yes", "-y", metavar="", help="Also run the upstream stages this one needs (else it names them and stops).")]
Save = Annotated[bool, typer.Option("--save", metavar="", help="Write this command's settings (and earlier command-line ones) to sefa.yaml.")]


def train(
    args: Annotated[Optional[list[str]], typer.Argument(help="[CONFIG.yaml] then key=value overrides, e.g. training.max_steps=2000 policy.head=mlp (on top of sefa.yaml's; kept for later commands, which say so, until `sefa config reset`; written to sefa.yaml only with --save)")] = None,
    preset: Annotated[Optional[str], typer.Option("--preset", help="Train with an installed preset's train config instead of a CONFIG.yaml (`sefa presets` lists them), e.g. --preset lerobot_camera_cpu.")] = None,
    resume: Annotated[bool, typer.Option(help="Continue the interrupted training of these settings (the workspace's, or --out's) from its last checkpoint, with its saved config; in a workspace, also a finished run of the same settings to a larger training.max_steps when its lr schedule differs (one of the same schedule is continued without asking).")] = False,
    force: Annotated[bool, typer.Option(help="Rebuild the run of these settings even if cached (other runs are kept); with --out, delete OUT and start over.")] = False,
    save: Save = False,
    device: Device = None,
    threads: Threads = None,
    out: Annotated[Optional[Path], typer.Option("--out", "-o", help="A run directory outside the workspace's stages (default: the workspace's train stage, runs/train/<run id>).")] = None,
    objective: Annotated[Optional[str], typer.Option(help="flow (the base rectified flow) or ddpm (the diffusion baseline, same network; give it its own --out).")] = None,
    workspace: Workspace = Path("."),
    as_json: JsonFlag = False,
) -> None:
    """Train the base rectified-flow policy, or the diffusion baseline, on the workspace's store.

    Each setting is its own run (runs/train/<run id>, `train` points at the current one); an
    interrupted run keeps its last checkpoint and the same command continues it. Works under
    torchrun (DDP) unchanged.

    Example: sefa train policy.head=mlp training.max_steps=2000 --threads 1 -w ws"""
    import shutil

    from sefa_cli.console import TrainProgress
    from sefa_model.distributed import DistContext
    from sefa_model.train.loop import train as run_train

    config, overrides = _split_config_args(args or [])
    config = _config_file(config, preset, "train")
    if objective:
        overrides.append(f"objective={objective}")
    flags: dict = {"train": overrides} if overrides else {}
    if config:
        flags["train_config"] = str(config.resolve())
    if not out:
        start_process(device, threads, workspace)
        _workspace_command(workspace, "train", flags, {"train"} if force else set(), as_json,
                           device, yes=True, save=save, resume=resume)
        return
    from sefa_pipelines.workspace import out_train_config

    if save:
        raise SefaInputError("--save writes the workspace's settings; a run with --out keeps its "
                             "own (in OUT/checkpoints/latest/config.json)", key="--save")
    cfg, store, notes = out_train_config(workspace, flags, device)
    start_process(device, threads, workspace)
    ctx = DistContext.from_env()
    run_dir = out
    rank0 = ctx.is_main
    if force and run_dir.exists() and rank0:
        shutil.rmtree(run_dir)
    with TrainProgress(enabled=rank0 and not as_json) as progress:
        for note in notes if rank0 else []:
            progress.log(note)
        result = run_train(cfg, run_dir, store, resume=resume, callbacks=progress.callbacks())
    if as_json and rank0:
        from dataclasses import asdict

        print(json.dumps(asdict(result), indent=2))


def _config_file(path: Optional[Path], preset: Optional[str], command: str) -> Optional[Path]:
    """The settings file a command was given: a path, or an installed preset by name (one of
    the two); a path that does not exist is refused here, naming the preset of that file name
    if one is installed."""
    from sefa_pipelines.presets import missing_file_hint, resolve

    if path is not None and preset is not None:
        raise SefaInputError(f"give a {'pipeline' if command == 'run' else 'config'} file or "
                             "--preset, not both", key="--preset")
    if preset is not None:
        return resolve(preset, command)
    if path is not None and not path.exists():
        raise SefaInputError(("no such pipeline file" if command == "run" else "file not found")
                             + missing_file_hint(path), file=str(path))
    return path


def _split_config_args(args: list[str]) -> tuple[Optional[Path], list[str]]:
    config = None
    overrides = []
    for a in args:
        if "=" not in a and a.endswith((".yaml", ".yml")) and config is None:
            config = Path(a)
        elif "=" in a:
            overrides.append(a)
        else:
            raise SefaInputError(f"'{a}' is neither a .yaml config nor a key=value override")
    return config, overrides


def _workspace_command(workspace: Path, command: str, flags: dict, force: set[str], as_json: bool,
                       device: Optional[str] = None, *, yes: bool = False, save: bool = False,
                       resume: bool = False, explicit: bool = False,
                       pipeline: Optional[Path] = None) -> list:
    """A command that runs workspace stages (its own and those they read, as the stage graph
    says; `run`: all): its settings (sefa.yaml + command-line flags, or `pipeline`'s), its
    upstream stages announced, progress shown, a JSON summary with --json."""
    from sefa_cli.console import TrainProgress
    from sefa_pipelines.workspace import (check_store, earlier_flags_note, machine_defaults,
                                          plan_pipeline_file, plan_settings, run_command)
    from sefa_model.distributed import context
    from sefa_model.data.features import rebuilding_damaged

    ctx = context()
    main_rank = ctx.is_main
    # --force also rebuilds a damaged features cache entry, which otherwise stops the command
    with TrainProgress(enabled=not as_json and main_rank) as progress, \
            rebuilding_damaged(bool(force)):
        # rank 0 reads the settings (and keeps them once every check passed); every rank runs
        # with rank 0's
        planned = None
        if main_rank:
            # the command's own settings first (a PIPELINE that needs --save), then the store;
            # both before any line says what it would keep (planning writes nothing)
            planned = (plan_pipeline_file(workspace, pipeline, save) if pipeline is not None
                       else plan_settings(workspace, flags, save=save))
            check_store(workspace, command)
        pipe, kept_flags, notes = ctx.broadcast(
            None if planned is None else (planned.pipe, planned.flags, planned.notes))
        pipe, defaults = machine_defaults(workspace, pipe, device)
        for note in notes:
            progress.log(note)
        check = _resume_check(workspace, resume) if resume else (lambda chosen: None)
        record = {"command": "sefa " + " ".join(sys.argv[1:]), "flags": kept_flags}
        try:
            results = run_command(workspace, pipe, force, command=command,
                                  yes=yes or explicit,
                                  interactive=sys.stdin.isatty() and not as_json,
                                  log=progress.log, on_step=progress.on_step, device=device,
                                  record=record, check=check, resume=resume,
                                  keep=planned.keep if planned is not None else lambda: None,
                                  training_notes=defaults)
        except KeyboardInterrupt as e:  # past typer, with what it kept (cli/console.py)
            raise Interrupted(e) from None
        if kept_flags and not flags and pipeline is None:  # said first, and again last
            progress.log(earlier_flags_note(kept_flags))
    if as_json and main_rank:
        print(json.dumps([{"stage": r.name, "ran": r.ran, "summary": r.manifest.get("summary")}
                          for r in results], indent=2, default=str))
    return results


def _resume_check(workspace: Path, resume: bool):
    def check(chosen) -> None:
        from sefa_pipelines.workspace import continuable_run, partial_runs, resumable_run

        from sefa_pipelines.runner import Workspace as Ws

        train = next(s for s in chosen if s.name == "train")
        if (resumable_run(workspace, train) is None and continuable_run(workspace, train) is None
                and Ws(workspace).status(train).state != "cached"):
            others = [p.relative_to(workspace).as_posix() for p in partial_runs(workspace, "train")]
            raise SefaInputError("nothing to resume: no interrupted training of the current "
                                 "settings" + (f" (interrupted runs of other settings: "
                                               f"{', '.join(others)})" if others else ""))
    return check


def _section(section: str, **values) -> dict:
    chosen = {k: v for k, v in values.items() if v is not None}
    return {section: chosen} if chosen else {}


def reflow(
    iters: Annotated[Optional[int], typer.Option(help="Reflow iterations (each its own cached artifact). Default: sefa.yaml's reflow.iters, else 1.")] = None,
    samples: Annotated[Optional[int], typer.Option(help="Noises per training window (K). Default: sefa.yaml's reflow.samples_per_window, else 10.")] = None,
    max_windows: Annotated[Optional[int], typer.Option(help="Use this many evenly spread training windows (quick runs). Default: sefa.yaml's reflow.max_windows, else every window.")] = None,
    align_rounds: Annotated[Optional[bool], typer.Option("--align-rounds/--no-align-rounds", help="Align each round's couplings (the align stage's eps) before the next round trains on them. Default: sefa.yaml's reflow.align_rounds, else no.")] = None,
    train_steps: Annotated[Optional[int], typer.Option("--train-steps", help="Training steps of each reflowed flow (rounds 2 and on). Default: sefa.yaml's reflow.train_steps, else the base flow's training.max_steps.")] = None,
    block_windows: Annotated[Optional[int], typer.Option("--block-windows", help="Windows per solved block (each block is one batched ODE solve, kept when finished: a Ctrl-C loses at most the block in progress; with rk45 the couplings depend on it). Default: sefa.yaml's reflow.batch_windows, else 256.")] = None,
    force: Annotated[bool, typer.Option(help="Rerun even if cached.")] = False,
    yes: Yes = False,
    save: Save = False,
    device: Device = None,
    threads: Threads = None,
    workspace: Workspace = Path("."),
    as_json: JsonFlag = False,
) -> None:
    """Generate reflow couplings from the base flow (and train reflowed flows for --iters > 1).

    Example: sefa reflow --iters 2 --samples 3 --max-windows 500 -w ws"""
    start_process(device, threads, workspace)
    _workspace_command(workspace, "reflow", _section("reflow", iters=iters, samples_per_window=samples,
                                                     max_windows=max_windows, align_rounds=align_rounds,
                                                     train_steps=train_steps,
                                                     batch_windows=block_windows),
                       {"reflow"} if force else set(), as_json, device, yes=yes, save=save)


def align(
    eps: Annotated[Optional[str], typer.Option(help="Replace a generated chunk by the expert's when closer than this (normalized units), or `auto`: the eps that replaces the nearest 20% of the couplings (the chosen eps is recorded and printed). Default: sefa.yaml's align.eps, else 0.1.")] = None,
    replace_fraction: Annotated[Optional[float], typer.Option(help="Choose eps from the data: the smallest that replaces this fraction (0 to 1) of the couplings, the nearest ones (--eps auto is 0.2).")] = None,
    matching_obs: Annotated[Optional[bool], typer.Option("--matching-obs/--same-window", help="Candidates from every window with a matching observation (the reference code's variant). Default: same window.")] = None,
    force: Annotated[bool, typer.Option(help="Rerun even if cached.")] = False,
    yes: Yes = False,
    save: Save = False,
    device: Device = None,
    threads: Threads = None,
    workspace: Workspace = Path("."),
    as_json: JsonFlag = False,
) -> None:
    """Selective alignment of the last reflow couplings to the expert chunks.

    Each eps is its own run (runs/align/<run id>): an eps sweep sits side by side.

    Example: sefa align --eps 0.5 -w ws   |   sefa align --eps auto -w ws"""
    variant = None if matching_obs is None else ("matching_obs" if matching_obs else "same_window")
    values = _eps_choice(eps, replace_fraction)
    if variant is not None:
        values["variant"] = variant
    start_process(device, threads, workspace)
    _workspace_command(workspace, "align", {"align": values} if values else {},
                       {"align"} if force else set(), as_json, device, yes=yes, save=save)
    from sefa_model.distributed import context

    if not as_json and context().is_main:
        from sefa_pipelines.report import alignment_report

        print(alignment_report(workspace / "align"))


def _eps_choice(eps: Optional[str], replace_fraction: Optional[float]) -> dict:
    """--eps E (clears a replace_fraction kept from an earlier command), --eps auto or
    --replace-fraction F (eps chosen from the data)."""
    from sefa_model.sefa.alignment import AUTO_FRACTION

    if eps is not None and replace_fraction is not None:
        raise SefaInputError("give --eps or --replace-fraction, not both", key="--eps")
    if replace_fraction is not None:
        return {"replace_fraction": replace_fraction}
    if eps is None:
        return {}
    if eps.strip().lower() == "auto":
        return {"replace_fraction": AUTO_FRACTION}
    try:
        value = float(eps)
    except ValueError:
        raise SefaInputError(f"'{eps}' is neither a number nor auto", key="--eps") from None
    return {"eps": value, "replace_fraction": None}


def distill(
    method: Annotated[Optional[str], typer.Option("--method", help="How the student is trained: reference (MSE at t = 0, the reference code's), rfpp (2-rectified-flow++), mean_flow or shortcut (distil the base flow on fresh noise; no couplings). docs/extending.md adds one. Default: sefa.yaml's distill.method, else reference.")] = None,
    align: Annotated[Optional[bool], typer.Option("--align/--no-align", help="On the aligned couplings (SeFA), or on the unaligned ones (the plain reflow baseline). Default: sefa.yaml's distill.align (or the last flag given), else aligned.")] = None,
    steps: Annotated[Optional[int], typer.Option("--steps", help="Euler steps the student samples with (network evaluations per chunk): 1, the one-step policy, or k, a student trained at the k Euler times. Default: sefa.yaml's distill.steps, else 1.")] = None,
    train_steps: Annotated[Optional[int], typer.Option("--train-steps", help="Training steps of the student. Default: sefa.yaml's distill.train_steps, else the base flow's training.max_steps.")] = None,
    force: Annotated[bool, typer.Option(help="Rerun even if cached.")] = False,
    yes: Yes = False,
    save: Save = False,
    device: Device = None,
    threads: Threads = None,
    workspace: Workspace = Path("."),
    as_json: JsonFlag = False,
) -> None:
    """Train the one-step policy on the aligned couplings.

    Example: sefa distill -w ws   (sefa distill --no-align: the plain reflow baseline;
    sefa distill --steps 2: a two-step student; sefa distill --method rfpp: another recipe)"""
    start_process(device, threads, workspace)
    _workspace_command(workspace, "distill", _section("distill", method=method, align=align, steps=steps,
                                                      train_steps=train_steps),
                       {"distill"} if force else set(), as_json, device, yes=yes, save=save)


def run(
    pipeline: Annotated[Optional[Path], typer.Argument(help="A pipeline YAML (default: WORKSPACE/sefa.yaml).")] = None,
    preset: Annotated[Optional[str], typer.Option("--preset", help="Run an installed preset pipeline instead of a PIPELINE file (`sefa presets` lists them), e.g. --preset lerobot_camera_cpu.")] = None,
    force: Annotated[list[str], typer.Option(help="Rerun this stage even if cached (repeatable).")] = [],
    save: Annotated[bool, typer.Option("--save", metavar="", help="Replace a sefa.yaml that has other settings than PIPELINE's (the old one kept as sefa.yaml.bak).")] = False,
    device: Device = None,
    threads: Threads = None,
    workspace: Workspace = Path("."),
    as_json: JsonFlag = False,
) -> None:
    """Run every stage in order; cached stages are skipped, an interrupted training continues.

    PIPELINE becomes the workspace's sefa.yaml when it has none; a sefa.yaml with other settings
    is replaced only with --save. On N GPUs: torchrun --nproc_per_node N -m sefa_cli.main run PIPELINE
    (the same manifests).

    Example: sefa run --preset pusht_lowdim -w ws   |   sefa run my_pipeline.yaml -w ws"""
    pipeline = _config_file(pipeline, preset, "run")  # before start_process reads the workspace
    if pipeline is None and save:
        raise SefaInputError("--save replaces sefa.yaml by a PIPELINE file's settings; none given",
                             key="--save")
    if pipeline is not None and not pipeline.is_file():
        raise SefaInputError("is not a file (a pipeline YAML expected)", file=str(pipeline))
    start_process(device, threads, workspace, pipeline)
    results = _workspace_command(workspace, "run", {}, set(force), as_json, device,
                                 explicit=True, pipeline=pipeline, save=save)
    from sefa_model.distributed import context

    if not as_json and context().is_main and any(r.name == "align" and r.ran for r in results):
        from sefa_pipelines.report import alignment_report

        print(alignment_report(workspace / "align"))  # as `sefa align` says it: histogram, warning


def presets(as_json: JsonFlag = False) -> None:
    """The settings shipped with sefa, by the name `sefa train --preset NAME` and `sefa run
    --preset NAME` take from any folder: what each is for, and its files.

    Example: sefa presets"""
    from sefa_cli.console import render_presets
    from sefa_pipelines.presets import presets as installed

    rows = [{"name": p.name, "for": p.about,
             "run": str(p.pipeline) if p.pipeline else None,
             "train": str(p.train_config) if p.train_config else None}
            for p in installed().values()]
    if as_json:
        print(json.dumps(rows, indent=2))
    else:
        render_presets(rows)
