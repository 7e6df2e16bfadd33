"""The `sefa` command. It parses arguments and calls library functions; nothing more."""

from __future__ import annotations

import json
import os
import sys


def _interrupted_while_starting() -> None:
    """A Ctrl-C while the libraries load (seconds, before `main` runs): no traceback, 130."""
    print("interrupted while starting: nothing was read or written", file=sys.stderr)
    if "--json" in sys.argv[1:]:
        print(json.dumps({"error": {"message": "interrupted", "kind": "interrupted",
                                    "exit_code": 130}}))
    exec("")  # see _forget_caught_interrupt: libraries run string execs while they are imported
    sys.exit(130)


try:
    from pathlib import Path
    from typing import Annotated, Optional

    import typer

    from cli.bench import bench_app
    from cli.convert import convert
    from cli.deploy import export, serve
    from cli.console import Reporter, render_recording, render_store
    from cli.paths import in_workspace
    from sefa_data import atomic
    from sefa_data.errors import SefaInputError
except KeyboardInterrupt:
    _interrupted_while_starting()

app = typer.Typer(add_completion=False, no_args_is_help=True,
                  context_settings={"help_option_names": ["-h", "--help"]},
                  help="Robot demonstrations to one-step visuomotor policies (Selective Flow Alignment).")


def _version(value: bool) -> None:
    if value:
        from importlib.metadata import PackageNotFoundError, version

        try:
            print(f"sefa {version('sefa')}")
        except PackageNotFoundError:
            print("sefa (not installed: running from a checkout)")
        raise typer.Exit()


@app.callback()
def _root(version: Annotated[bool, typer.Option("--version", callback=_version, is_eager=True,
                                                 help="Print the version and exit.")] = False) -> None:
    """Robot demonstrations to one-step visuomotor policies (Selective Flow Alignment)."""

DEFAULT_STORE = "dataset.zarr"

app.add_typer(bench_app, name="bench", help="Measure latency (sefa bench latency) and data throughput (sefa bench data).")

Workspace = Annotated[Path, typer.Option("--workspace", "-w", help="Workspace directory.")]
JsonFlag = Annotated[bool, typer.Option("--json", is_flag=True, show_default=False, metavar="", help="Print a JSON summary on stdout.")]
Device = Annotated[Optional[str], typer.Option(
    help="auto, cpu, cuda, cuda:N or mps (default: `device` in sefa.yaml, else auto). Under "
         "torchrun, cuda means each process's LOCAL_RANK GPU.")]
Threads = Annotated[Optional[int], typer.Option(
    "--threads", min=1,
    help="CPU threads for torch (default: `threads` in sefa.yaml, else torch's own choice). On a "
         "busy machine 1 is often much faster.")]
Yes = Annotated[bool, typer.Option("--yes", "-y", metavar="", help="Also run the upstream stages this one needs (else it names them and stops).")]
Save = Annotated[bool, typer.Option("--save", metavar="", help="Write this command's settings (and earlier command-line ones) to sefa.yaml.")]


def _start(device: Optional[str], threads: Optional[int] = None,
           workspace: Optional[Path] = None, pipeline: Optional[Path] = None) -> None:
    """Under torchrun: join the process group on the chosen device before anything else."""
    from sefa_model.distributed import ensure_process_group, resolve_device

    if device is not None:
        resolve_device(device)  # an unknown or absent device stops the command before any work
    _set_threads(threads, workspace, pipeline)
    ensure_process_group(device or "auto")


def _set_threads(threads: Optional[int], workspace: Optional[Path],
                 pipeline: Optional[Path] = None) -> None:
    """`threads` of the settings the command runs with: PIPELINE's for `sefa run PIPELINE`."""
    if threads is None and workspace is not None and (
            pipeline is not None or (workspace / "sefa.yaml").exists()):
        from pipelines.stages import load_pipeline

        threads = load_pipeline(workspace, pipeline).threads
    if threads is not None:
        import torch

        torch.set_num_threads(threads)


def _pairs(items: list[str], what: str) -> dict[str, str]:
    out = {}
    for item in items:
        if "=" not in item:
            raise SefaInputError(f"{what} '{item}' is not of the form old=new")
        a, b = item.split("=", 1)
        out[a] = b
    return out


@app.command()
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
        from sefa_data.ingest import detect_format

        if len(inputs) != 1:
            raise SefaInputError(f"--scaffold reads one recording, got {len(inputs)}")
        fmt = detect_format(inputs[0])
        notes: list[str] = []
        if fmt == "hdf5":
            from sefa_data.readers.hdf5 import scaffold_key_map as scaffold_map
        elif fmt == "ros":
            from sefa_data.readers.ros import scaffold_topic_map_noted

            def scaffold_map(path, fps):
                text, warning = scaffold_topic_map_noted(path, fps)
                if warning:  # said after the map, which is where the field is selected
                    notes.append(warning)
                return text
        else:
            raise SefaInputError(f"a {'LeRobot dataset' if fmt == 'lerobot' else 'Zarr store'} "
                                 "needs no map (choose keys with --key and --rename)",
                                 file=str(inputs[0]))
        text = scaffold_map(inputs[0], fps)
        if topic_map is None:
            sys.stdout.write(text)
        else:
            _write_new(topic_map, text)
            rep.line(f"wrote {topic_map}")
        for line in notes:
            rep.line(line)
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
        raise _Interrupted(e) from None
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


def _write_new(path: Path, text: str) -> None:
    if path.is_dir():
        raise SefaInputError("is a directory; --map names the YAML file to write", file=str(path))
    atomic.write_text(path, text)


@app.command()
def inspect(
    path: Annotated[Optional[Path], typer.Argument(help="A sefa store, a bag/MCAP recording, an HDF5 file or a LeRobot dataset folder.")] = None,
    verify: Annotated[bool, typer.Option("--verify", help="Store: check every chunk's checksum, images included (a plain inspect checks presence and sizes, and the checksums of all but image chunks).")] = False,
    workspace: Workspace = Path("."),
    as_json: JsonFlag = False,
) -> None:
    """Show a store (episodes, keys, statistics, masks, provenance, integrity), a recording (topics, rates, gaps, skew) or an HDF5 file (demos, keys, what ingest reads)."""
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
        from cli.console import render_hdf5
        from sefa_data.readers.hdf5 import inspect_hdf5

        summary = inspect_hdf5(path)
        render = render_hdf5
    elif fmt == "lerobot":
        from cli.console import render_lerobot
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


@app.command()
def info(as_json: JsonFlag = False) -> None:
    """Versions of sefa and its libraries, for bug reports."""
    import platform

    from sefa_data.store.zarr_store import package_versions

    data = {"python": platform.python_version(), "platform": platform.platform(),
            **package_versions()}
    try:
        import torch

        data["cuda"] = torch.cuda.is_available()
    except ImportError:
        pass
    print(json.dumps(data, indent=2) if as_json else "\n".join(f"{k}: {v}" for k, v in data.items()))


@app.command(context_settings={"allow_extra_args": True, "ignore_unknown_options": False})
def train(
    args: Annotated[Optional[list[str]], typer.Argument(help="[CONFIG.yaml] then key=value overrides, e.g. training.max_steps=2000 policy.head=mlp (on top of sefa.yaml's; kept for later commands, written to sefa.yaml only with --save)")] = None,
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

    from cli.console import TrainProgress
    from sefa_model.distributed import DistContext
    from sefa_model.training import train as run_train

    config, overrides = _split_config_args(args or [])
    if objective:
        overrides.append(f"objective={objective}")
    flags: dict = {"train": overrides} if overrides else {}
    if config:
        flags["train_config"] = str(config.resolve())
    if not out:
        _start(device, threads, workspace)
        _workspace_command(workspace, "train", flags, {"train"} if force else set(), as_json,
                           device, yes=True, save=save, resume=resume)
        return
    from pipelines.workspace import out_train_config

    if save:
        raise SefaInputError("--save writes the workspace's settings; a run with --out keeps its "
                             "own (in OUT/checkpoints/latest/config.json)", key="--save")
    cfg, store, notes = out_train_config(workspace, flags, device)
    _start(device, threads, workspace)
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
    from cli.console import TrainProgress
    from pipelines.workspace import (check_store, machine_defaults, plan_pipeline_file,
                                     plan_settings, run_command)
    from sefa_model.distributed import context
    from sefa_model.features import rebuilding_damaged

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
        except KeyboardInterrupt as e:  # past typer, with what it kept (see _Interrupted)
            raise _Interrupted(e) from None
    if as_json and main_rank:
        print(json.dumps([{"stage": r.name, "ran": r.ran, "summary": r.manifest.get("summary")}
                          for r in results], indent=2, default=str))
    return results


def _resume_check(workspace: Path, resume: bool):
    def check(chosen) -> None:
        from pipelines.workspace import continuable_run, partial_runs, resumable_run

        from pipelines.runner import Workspace as Ws

        train = next(s for s in chosen if s.name == "train")
        if (resumable_run(workspace, train) is None and continuable_run(workspace, train) is None
                and Ws(workspace).status(train).state != "cached"):
            others = [p.relative_to(workspace).as_posix() for p in partial_runs(workspace, "train")]
            raise SefaInputError("nothing to resume: no interrupted training of the current "
                                 "settings" + (f" (interrupted runs of other settings: "
                                               f"{', '.join(others)})" if others else ""))
    return check


def _workspace_device(workspace: Path) -> str:
    """`device` of the workspace's sefa.yaml, else auto."""
    from pipelines.stages import load_pipeline

    return load_pipeline(workspace).device or "auto"


def _section(section: str, **values) -> dict:
    chosen = {k: v for k, v in values.items() if v is not None}
    return {section: chosen} if chosen else {}


@app.command()
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
    _start(device, threads, workspace)
    _workspace_command(workspace, "reflow", _section("reflow", iters=iters, samples_per_window=samples,
                                                     max_windows=max_windows, align_rounds=align_rounds,
                                                     train_steps=train_steps,
                                                     batch_windows=block_windows),
                       {"reflow"} if force else set(), as_json, device, yes=yes, save=save)


@app.command()
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
    _start(device, threads, workspace)
    _workspace_command(workspace, "align", {"align": values} if values else {},
                       {"align"} if force else set(), as_json, device, yes=yes, save=save)
    from sefa_model.distributed import context

    if not as_json and context().is_main:
        from pipelines.report import alignment_report

        print(alignment_report(workspace / "align"))


def _eps_choice(eps: Optional[str], replace_fraction: Optional[float]) -> dict:
    """--eps E (clears a replace_fraction kept from an earlier command), --eps auto or
    --replace-fraction F (eps chosen from the data)."""
    from sefa_model.alignment import AUTO_FRACTION

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


@app.command()
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
    _start(device, threads, workspace)
    _workspace_command(workspace, "distill", _section("distill", method=method, align=align, steps=steps,
                                                      train_steps=train_steps),
                       {"distill"} if force else set(), as_json, device, yes=yes, save=save)


@app.command()
def run(
    pipeline: Annotated[Optional[Path], typer.Argument(help="A pipeline YAML (default: WORKSPACE/sefa.yaml).")] = None,
    force: Annotated[list[str], typer.Option(help="Rerun this stage even if cached (repeatable).")] = [],
    save: Annotated[bool, typer.Option("--save", metavar="", help="Replace a sefa.yaml that has other settings than PIPELINE's (the old one kept as sefa.yaml.bak).")] = False,
    device: Device = None,
    threads: Threads = None,
    workspace: Workspace = Path("."),
    as_json: JsonFlag = False,
) -> None:
    """Run every stage in order; cached stages are skipped, an interrupted training continues.

    PIPELINE becomes the workspace's sefa.yaml when it has none; a sefa.yaml with other settings
    is replaced only with --save. On N GPUs: torchrun --nproc_per_node N -m cli.main run PIPELINE
    (the same manifests).

    Example: sefa run pipelines/pusht_small.yaml -w ws"""
    if pipeline is None and save:
        raise SefaInputError("--save replaces sefa.yaml by a PIPELINE file's settings; none given",
                             key="--save")
    if pipeline is not None and not pipeline.is_file():  # before _start reads the workspace
        raise SefaInputError("no such pipeline file" if not pipeline.exists()
                             else "is not a file (a pipeline YAML expected)", file=str(pipeline))
    _start(device, threads, workspace, pipeline)
    _workspace_command(workspace, "run", {}, set(force), as_json, device, explicit=True,
                       pipeline=pipeline, save=save)


@app.command()
def status(workspace: Workspace = Path("."), as_json: JsonFlag = False) -> None:
    """Every stage of the workspace (ingest, train, reflow, align, distill, eval): state, path,
    key metric, duration, and the next command.

    Example: sefa status -w ws"""
    from pipelines.overview import overview

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
app.add_typer(config_app, name="config")


@config_app.command("show")
def config_show(workspace: Workspace = Path("."), as_json: JsonFlag = False) -> None:
    """The resolved settings with every key: sefa.yaml, the command-line settings kept on top of
    it, the machine's defaults, and the full train config of each stage.

    Example: sefa config show -w ws"""
    import yaml

    from pipelines.overview import resolved_config

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
    from pipelines.workspace import set_setting

    print(set_setting(workspace, key, value))


@app.command(name="eval")
def eval_(
    checkpoints: Annotated[Optional[list[Path]], typer.Argument(help="Checkpoints or run dirs, a relative one looked for in the workspace first (default: every stage of the workspace).")] = None,
    offline: Annotated[bool, typer.Option("--offline", help="Validation action MSE and multimodality on the store (no simulator).")] = False,
    env: Annotated[Optional[str], typer.Option(help="Closed-loop rollouts in simulation: pusht, robosuite:Lift, metaworld:TASK (reach, pick-place, ...) or metaworld:GROUP (easy, medium, hard, very_hard, all).")] = None,
    n_test: Annotated[int, typer.Option(help="Rollout episodes (test seeds from --start-seed).")] = 50,
    start_seed: Annotated[int, typer.Option(help="First test seed (Diffusion Policy: 100000).")] = 100000,
    max_steps: Annotated[Optional[int], typer.Option(help="Environment steps per rollout (default: Push-T and Lift 300, Meta-World its own 500).")] = None,
    solver: Annotated[Optional[str], typer.Option(help="Override the checkpoint's solver (flow: euler, midpoint, rk4, rk45, rk45-ps, dop853-ps; diffusion baseline: ddpm, ddim).")] = None,
    steps: Annotated[Optional[int], typer.Option(help="Steps for a fixed-step solver or the diffusion sampler.")] = None,
    windows: Annotated[Optional[int], typer.Option(help="Validation windows to evaluate, evenly spread. Default: the ones training validated on (the checkpoint's training.val_sample_windows), with its seed, so the action MSE is training's validation action MSE.")] = None,
    samples: Annotated[int, typer.Option(help="Samples per observation for the multimodality measure.")] = 8,
    key_map: Annotated[Optional[list[str]], typer.Option("--key-map", help="Rollouts: NAME=KEY feeds the simulator's observation NAME (Push-T: keypoint, state, agent_pos, img) to the policy's KEY, as `sefa serve --key-map` maps a client's names. LeRobot's Push-T names (observation.image, observation.state) are mapped without it. Repeatable.")] = None,
    out: Annotated[Optional[Path], typer.Option("--out", "-o", help="Rollouts: also write eval_log.json to this folder (one checkpoint). Every result is kept in WORKSPACE/evals/<mode>-<key>/ regardless.")] = None,
    force: Annotated[bool, typer.Option(help="Evaluate again even if this evaluation is cached.")] = False,
    device: Device = None,
    threads: Threads = None,
    workspace: Workspace = Path("."),
    as_json: JsonFlag = False,
) -> None:
    """Evaluate checkpoints: closed-loop rollouts (--env) or action MSE, NFE and sample spread on the store (--offline).

    Results are cached by (checkpoint content, solver, seeds, settings) in WORKSPACE/evals/: the
    same evaluation again is instant, other seeds or solvers get their own folder; `sefa
    results` lists them all. Under torchrun the rollout seeds are split across the processes;
    rank 0 writes the log.

    Example: sefa eval --env pusht --n-test 10 -w ws   |   sefa eval --offline -w ws"""
    from cli.console import TrainProgress
    from pipelines.evals import (EvalRequest, check_request, default_checkpoints, evaluate,
                                 result_rows)
    from sefa_model.distributed import context

    from pipelines.options import check_options

    from sefa_deploy.server import parse_key_map

    try:
        names = parse_key_map(key_map or [])
    except ValueError as e:
        raise SefaInputError(str(e).replace("an openpi observation name", "a simulator's "
                                            "observation name"), key="--key-map") from None
    env = check_request(env, offline, names)
    check_options("eval", {"--n-test": n_test, "--start-seed": start_seed, "--max-steps": max_steps,
                           "--steps": steps, "--windows": windows, "--samples": samples})
    _start(device, threads, workspace)
    device = device or _workspace_device(workspace)
    main_rank = context().is_main
    request = EvalRequest(env, n_test, start_seed, max_steps, solver, steps, windows, samples,
                          tuple(names.items()))
    checkpoints = ([in_workspace(workspace, c) for c in checkpoints] if checkpoints
                   else default_checkpoints(workspace))
    with TrainProgress(enabled=main_rank and not as_json) as progress:
        records = evaluate(workspace, checkpoints, request, device=device, force=force, out=out,
                           is_main=main_rank, log=progress.log)
    if not main_rank:
        return
    rows = result_rows(workspace, records, env)
    if as_json:
        print(json.dumps(rows, indent=2))
    elif env is not None:
        for log in rows:
            print(f"{log['checkpoint']}: {log['kind']}, {log['solver']}: mean score "
                  f"{log['test/mean_score']:.3f}, success {log['test/success_rate']:.0%} over "
                  f"{log['n_test']} seeds from {log['test_start_seed']} ({log['eval_log']})")
    else:
        _offline_table(rows)


def _offline_table(rows: list[dict]) -> None:
    from rich.table import Table

    from cli.console import out as console_out

    first = rows[0] if rows else {}
    t = Table(title=f"offline evaluation ({first.get('windows', '')} {first.get('split', '')} "
                    f"windows, {first.get('samples', '')} samples each)")
    for col in ("checkpoint", "kind", "solver", "NFE", "action MSE", "mean-action MSE",
                "best-of-K MSE", "spread / expert"):
        t.add_column(col)
    notes = set()
    for r in rows:
        mean = r.get("mean_action_mse")
        spread = f"{r['spread']:.3f} / {r['expert_spread']:.3f}"
        if r.get("spread_note"):
            spread += " (no ratio)"
            notes.add(r["spread_note"])
        t.add_row(r["checkpoint"], r["kind"], f"{r['solver']}{'' if r['steps'] is None else '-' + str(r['steps'])}",
                  str(r["nfe"]), f"{r['action_mse']:.4g}", "-" if mean is None else f"{mean:.4g}",
                  f"{r['action_mse_best_of_k']:.4g}", spread)
    console_out.print(t)
    # the one row worth a sentence: the baseline beating the policies
    beaten = [r["checkpoint"] for r in rows if r.get("mean_action_mse") is not None
              and r["mean_action_mse"] <= r["action_mse"]]
    if beaten:
        console_out.print(f"always predicting the training set's mean action beats "
                          f"{', '.join(beaten)} on these windows")
    for note in sorted(notes):
        console_out.print(note)
    if rows:
        console_out.print("action MSE: sample 0 of each window, training's validation definition "
                          "(the same windows and noise as training's with the default --windows)")


@app.command()
def results(workspace: Workspace = Path("."), as_json: JsonFlag = False) -> None:
    """Every evaluation kept in the workspace (WORKSPACE/evals/), one row each.

    Example: sefa results -w ws"""
    from rich.table import Table

    from cli.console import out as console_out
    from pipelines.evals import all_results, key_metric

    rows = all_results(workspace)
    if as_json:
        print(json.dumps(rows, indent=2))
        return
    if not rows:
        print("no evaluations yet: sefa eval --offline, or sefa eval --env pusht")
        return
    cells = [_result_cells(r) for r in rows]
    t = Table(title=f"evaluations in {workspace}/evals")
    for col in cells[0]:
        # names are copied into the next command: never cut (the result column wraps instead)
        t.add_column(col, no_wrap=col in WHOLE_CELLS)
    for c in cells:
        t.add_row(*c.values())
    if _narrowest_table(cells) > console_out.width:
        # too narrow for the table (an 80-column terminal): one evaluation per two lines
        for c in cells:
            console_out.print(f"{c['folder']}  {c['checkpoint (run)']}  {c['kind']}, {c['mode']}, "
                              f"{c['solver']}, NFE {c['NFE']}\n    {c['result']} ({c['when']})",
                              highlight=False, markup=False, soft_wrap=True)
        return
    console_out.print(t)


WHOLE_CELLS = ("checkpoint (run)", "folder")


def _narrowest_table(cells: list[dict[str, str]]) -> int:
    """The columns a table of these cells needs at the least: whole names unbroken, the other
    cells wrapped at spaces (rich squeezes a narrower table into empty columns)."""
    def least(col: str, text: str) -> int:
        return len(text) if col in WHOLE_CELLS else max(map(len, text.split()), default=0)
    return 1 + sum(3 + max(least(col, col), *(least(col, c[col]) for c in cells))
                   for col in cells[0])


def _result_cells(r: dict) -> dict[str, str]:
    """One evaluation as `sefa results` prints it, column by column."""
    from pipelines.evals import key_metric

    res = r["result"]
    if r["mode"] == "offline":
        metric = key_metric(r)
        nfe = str(res["nfe"])
    else:
        metric = (f"score {res['test/mean_score']:.3f}, success {res['test/success_rate']:.0%} "
                  f"({res['n_test']} seeds from {res['test_start_seed']})")
        # per predicted chunk, the mean over the rollouts (older logs did not record it)
        nfe = "-" if res.get("nfe") is None else f"{res['nfe']:g}"
    solver = res.get("solver") or "-"
    if r["mode"] == "offline" and res.get("steps") is not None:
        solver += f"-{res['steps']}"
    return {"checkpoint (run)": f"{r['checkpoint']} ({r['checkpoint_run']})",
            "kind": res.get("kind", "-"), "mode": r["mode"], "solver": solver, "NFE": nfe,
            "result": metric, "when": r["created"].replace("T", " ")[:16], "folder": r["folder"]}


@app.command()
def collect(
    out: Annotated[Path, typer.Argument(help="The HDF5 file to write (robomimic layout).")],
    env: Annotated[str, typer.Option(help="robosuite:Lift, or metaworld:TASK (one of Meta-World's 50 tasks: reach, pick-place, ...), each with its scripted expert.")] = "robosuite:Lift",
    episodes: Annotated[int, typer.Option(help="Episodes to attempt; only successful ones are kept.")] = 100,
    seed: Annotated[int, typer.Option(help="Episode i resets with seed + i (Meta-World: the seed fixes the object and goal positions).")] = 0,
    cameras: Annotated[bool, typer.Option(help="Also record agentview and eye-in-hand images (Lift only).")] = False,
    as_json: JsonFlag = False,
) -> None:
    """Record scripted expert demonstrations headless (no download).

    Example: sefa collect demos.hdf5 --env metaworld:reach --episodes 10"""
    from pipelines.evals import METAWORLD

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
    if metaworld:
        summary = collect_metaworld(out, env.removeprefix(METAWORLD), episodes, seed=seed)
        why = "info['success'] was never set within Meta-World's 500 steps"
    else:
        summary = collect_lift(out, episodes, seed=seed, cameras=cameras)
        why = "the cube was not lifted within the step limit"
    if as_json:
        print(json.dumps(summary, indent=2))
        return
    print(f"{out}: {summary['successful']}/{summary['attempted']} successful episodes kept "
          f"({summary['success_rate']:.0%}), {summary['steps']} steps")
    if summary["failed_seeds"]:  # dropped demos are said, not only counted
        print(f"not kept ({why}): seeds {', '.join(map(str, summary['failed_seeds']))}",
              file=sys.stderr)


@app.command()
def demo(workspace: Workspace = Path("runs/demo"), as_json: JsonFlag = False) -> None:
    """The built-in default, no downloads: scripted Lift demos through every SeFA stage.

    Records the demonstrations, ingests them, runs the pipeline and reports the policies."""
    from cli.console import TrainProgress, render_policy
    from pipelines.builtin_demo import run_demo

    with TrainProgress(enabled=not as_json) as progress:
        summary = run_demo(workspace, log=progress.log, on_step=progress.on_step)
    if as_json:
        print(json.dumps(summary, indent=2))
    else:
        render_store(summary["store"])
        render_policy(summary["policy"])


def _error_exit(line: str, as_json: bool, code: int = 1, error: SefaInputError | None = None,
                kind: str = "input") -> None:
    """One line on stderr; with --json also a JSON error object on stdout, for scripts."""
    print(f"error: {line}", file=sys.stderr)
    if as_json:
        fields = {"file": error.file, "key": error.key, "what": error.what, "where": error.where} \
            if error is not None else {}
        print(json.dumps({"error": {"message": line, "kind": kind, "exit_code": code, **fields}},
                         indent=2))
    sys.exit(code)


def _os_error_line(e: OSError) -> str:
    where = f"{e.filename}: " if e.filename else ""
    return f"{where}{e.strerror or e} (an operating system error while reading or writing)"


# deployment (cli/deploy.py): after the training and evaluation commands in `sefa --help`
app.command()(export)
app.command()(serve)
# LeRobot out (cli/convert.py, issue 21)
app.command()(convert)


# A Ctrl-C carried past typer (cli/console.py; `sefa convert` raises it too)
from cli.console import Interrupted as _Interrupted  # noqa: E402


def _interrupted_line(e: BaseException) -> str:
    """The interrupt's own line when it has one (what an ingest appended, what a stage kept);
    else the stage runner's promise."""
    x = e.interrupt if isinstance(e, _Interrupted) else e
    return getattr(x, "line", None) or \
        "interrupted: stores and artifacts are as they were before this stage"


def _caused_by_interrupt(e: BaseException) -> bool:
    """An error raised *from* a KeyboardInterrupt is the interrupt: Python 3.11 turns one that
    lands while a class is created (`__set_name__`, in a library's import) into "RuntimeError:
    Error calling __set_name__", which read as a bug in sefa."""
    seen = set()
    while e is not None and id(e) not in seen:
        if isinstance(e, KeyboardInterrupt):
            return True
        seen.add(id(e))
        e = e.__cause__
    return False


def _interrupt_exit(e: BaseException, as_json: bool) -> None:
    try:
        print(_interrupted_line(e), file=sys.stderr, flush=True)
        if as_json:
            print(json.dumps({"error": {"message": "interrupted", "kind": "interrupted",
                                        "exit_code": 130}}), flush=True)
    except OSError:
        # `sefa ... | tee log`: Ctrl-C reached tee too and the pipe is gone (README: `tee -i`);
        # the interrupt is still the exit status, not an error while saying so
        _quiet_broken_streams()
    sys.exit(130)


def _quiet_broken_streams() -> None:
    """Point stdout and stderr at /dev/null, so that Python's flush at exit does not print
    "Exception ignored ... BrokenPipeError" into a pipe nobody reads."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    for stream in (sys.stdout, sys.stderr):
        try:
            os.dup2(devnull, stream.fileno())
        except (OSError, ValueError):
            pass


def _forget_caught_interrupt() -> None:
    """CPython (3.8 to 3.13 at least) raises a process-wide "unhandled KeyboardInterrupt" flag
    when a KeyboardInterrupt ends the top level of any *string* exec/eval (run_eval_code_obj),
    even one that is caught further up, and under `python -m` (torchrun, the tests) Py_RunMain
    then kills the process with SIGINT (-2) instead of exiting 130. Libraries run such strings
    while they are imported (matplotlib's, imported at a training's first checkpoint, many), so a
    Ctrl-C landing there made `sefa` exit -2 now and then. Every string exec clears the flag."""
    exec("")


def main() -> None:
    as_json = "--json" in sys.argv[1:]
    try:
        # In this mode click returns typer.Exit's code, and 130 after catching a Ctrl-C itself.
        rc = app(standalone_mode=False)
        if rc == 130:
            raise KeyboardInterrupt
        sys.exit(rc if isinstance(rc, int) else 0)
    except SefaInputError as e:
        _error_exit(e.line(), as_json, error=e)
    except (KeyboardInterrupt, typer.Abort, _Interrupted) as e:
        _interrupt_exit(e, as_json)
    except OSError as e:  # EIO, a full disk, a file that vanished: the system's words, one line
        _error_exit(_os_error_line(e), as_json, kind="os")
    except MemoryError:
        _error_exit("out of memory (an input or a setting asks for more than this machine has)",
                    as_json, kind="memory")
    except Exception as e:
        if type(e).__name__ == "SolverFailed":  # sefa_model.solvers, not imported at start-up
            _error_exit(f"{' '.join(str(e).split())} (the policy's velocity field is not finite "
                        "or too stiff here: did its training diverge?)", as_json, kind="solver")
        if _caused_by_interrupt(e):
            _interrupt_exit(e, as_json)
        if hasattr(e, "show") and hasattr(e, "exit_code"):  # click's usage errors (typer vendors click)
            e.show()
            if as_json:
                print(json.dumps({"error": {"message": e.format_message(), "kind": "usage",
                                            "exit_code": e.exit_code}}))
            sys.exit(e.exit_code)
        if os.environ.get("SEFA_DEBUG"):
            raise
        text = " ".join(str(e).split())[:300]
        _error_exit(f"unexpected {type(e).__name__}: {text} (a bug in sefa: rerun with "
                    "SEFA_DEBUG=1 for the traceback and report it)", as_json, kind="internal")
    finally:  # whatever the exit: a Ctrl-C caught on the way must not turn it into -2
        _forget_caught_interrupt()


if __name__ == "__main__":
    main()
