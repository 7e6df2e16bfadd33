"""The `sefa` command. It parses arguments and calls library functions; nothing more."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path
from typing import Annotated, Optional

import typer

from cli.bench import bench_app
from cli.deploy import export, serve
from cli.console import Reporter, render_recording, render_store
from sefa_data.errors import SefaInputError

app = typer.Typer(add_completion=False, no_args_is_help=True,
                  help="Robot demonstrations to one-step visuomotor policies (Selective Flow Alignment).")

DEFAULT_STORE = "dataset.zarr"

app.add_typer(bench_app, name="bench", help="Measure latency (sefa bench latency) and data throughput (sefa bench data).")

Workspace = Annotated[Path, typer.Option("--workspace", "-w", help="Workspace directory.")]
JsonFlag = Annotated[bool, typer.Option("--json", help="Print a JSON summary on stdout.")]
Device = Annotated[Optional[str], typer.Option(
    help="auto, cpu, cuda, cuda:N or mps (default: `device` in sefa.yaml, else auto). Under "
         "torchrun, cuda means each process's LOCAL_RANK GPU.")]


def _start(device: Optional[str]) -> None:
    """Under torchrun: join the process group on the chosen device before anything else."""
    from sefa_model.distributed import ensure_process_group, resolve_device

    if device is not None:
        resolve_device(device)  # an unknown or absent device stops the command before any work
    ensure_process_group(device or "auto")


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
    inputs: Annotated[list[Path], typer.Argument(help="Recordings: .bag, .mcap, ROS 2 bag dirs, .hdf5, .zarr, .zarr.zip")],
    out: Annotated[Optional[Path], typer.Option("--out", "-o", help=f"Store to append to (default: WORKSPACE/{DEFAULT_STORE}).")] = None,
    topic_map: Annotated[Optional[Path], typer.Option("--map", "-m", help="Topic map YAML (ROS bags, MCAP), or HDF5 key map YAML (see --scaffold).")] = None,
    fps: Annotated[Optional[float], typer.Option(help="Frame rate of the store (required for a new store from Zarr input).")] = None,
    rename: Annotated[list[str], typer.Option(help="Zarr import: rename a key, old=new (repeatable).")] = [],
    key: Annotated[list[str], typer.Option(help="Zarr import: only this source key (repeatable; default all).")] = [],
    obs_key: Annotated[list[str], typer.Option(help="HDF5: observation keys to read (repeatable; default all).")] = [],
    action_key: Annotated[str, typer.Option(help="HDF5: the action dataset name.")] = "actions",
    filter_key: Annotated[Optional[str], typer.Option(help="HDF5: only demos in mask/<filter_key>.")] = None,
    hdf5_key: Annotated[list[str], typer.Option(help="HDF5: key map for other layouts, key=path/in/demo (repeatable).")] = [],
    skip_bad_demos: Annotated[bool, typer.Option(help="HDF5: skip a demo whose observation is missing or of another length than its actions (with a warning) instead of failing.")] = False,
    zarr_format: Annotated[int, typer.Option(help="Zarr format of a new store (2 or 3).")] = 2,
    scaffold: Annotated[bool, typer.Option(help="Write a starter map (a bag's topics, an HDF5 file's datasets) to --map or stdout and exit.")] = False,
    dry_run: Annotated[bool, typer.Option(help="Read and check everything; write nothing.")] = False,
    skip_failed: Annotated[bool, typer.Option(help="Go on past bad inputs and list them at the end.")] = False,
    workspace: Workspace = Path("."),
    as_json: JsonFlag = False,
) -> None:
    """Append recordings to a Zarr episode store (Diffusion Policy layout)."""
    from sefa_data.hdf5_reader import Hdf5Options
    from sefa_data.ingest import IngestOptions, ingest as run_ingest

    rep = Reporter(quiet=as_json)
    if scaffold:
        from sefa_data.ingest import detect_format

        if len(inputs) != 1:
            raise SefaInputError(f"--scaffold reads one recording, got {len(inputs)}")
        fmt = detect_format(inputs[0])
        if fmt == "hdf5":
            from sefa_data.hdf5_reader import scaffold_key_map as scaffold_map
        elif fmt == "ros":
            from sefa_data.ros_reader import scaffold_topic_map as scaffold_map
        else:
            raise SefaInputError("a Zarr store needs no map (choose keys with --key and "
                                 "--rename)", file=str(inputs[0]))
        text = scaffold_map(inputs[0], fps)
        if topic_map is None:
            sys.stdout.write(text)
        else:
            _write_new(topic_map, text)
            rep.line(f"wrote {topic_map}")
        return
    if zarr_format not in (2, 3):
        raise SefaInputError(f"--zarr-format must be 2 or 3, got {zarr_format}")
    options = IngestOptions(
        fps=fps, topic_map=str(topic_map) if topic_map else None,
        renames=_pairs(rename, "--rename"), keys=key or None,
        hdf5=Hdf5Options(obs_keys=obs_key or None, action_key=action_key, filter_key=filter_key,
                         key_map=_pairs(hdf5_key, "--hdf5-key"), skip_bad_demos=skip_bad_demos),
        zarr_format=zarr_format, skip_failed=skip_failed, dry_run=dry_run)
    store_path = out or workspace / DEFAULT_STORE
    with rep.status(f"ingesting {len(inputs)} input(s) into {store_path}"):
        report = run_ingest(inputs, store_path, options, log=rep.line)
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
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    tmp.replace(path)


@app.command()
def inspect(
    path: Annotated[Optional[Path], typer.Argument(help="A sefa store, a bag/MCAP recording or an HDF5 file.")] = None,
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
        from sefa_data.inspect import store_summary

        summary = store_summary(path, verify=verify)
        render = render_store
    elif fmt == "hdf5":
        from cli.console import render_hdf5
        from sefa_data.hdf5_reader import inspect_hdf5

        summary = inspect_hdf5(path)
        render = render_hdf5
    else:
        from sefa_data.ros_reader import inspect_recording

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

    from sefa_data.zarr_store import package_versions

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
    args: Annotated[Optional[list[str]], typer.Argument(help="[CONFIG.yaml] then key=value overrides, e.g. training.max_steps=2000 policy.head=mlp")] = None,
    resume: Annotated[bool, typer.Option(help="Continue the run in OUT from its latest checkpoint (with its saved config).")] = False,
    force: Annotated[bool, typer.Option(help="Delete an existing run in OUT and start over.")] = False,
    device: Device = None,
    out: Annotated[Optional[Path], typer.Option("--out", "-o", help="Run directory (default: WORKSPACE/train).")] = None,
    objective: Annotated[Optional[str], typer.Option(help="flow (the base rectified flow) or ddpm (the diffusion baseline, same network; give it its own --out).")] = None,
    workspace: Workspace = Path("."),
    as_json: JsonFlag = False,
) -> None:
    """Train the base rectified-flow policy, or the diffusion baseline, on the workspace's store.

    Works under torchrun (DDP) unchanged."""
    import shutil

    from cli.console import TrainProgress
    from sefa_model.config import load_train_config
    from sefa_model.distributed import DistContext
    from sefa_model.training import train as run_train

    config, overrides = _split_config_args(args or [])
    if objective:
        overrides.append(f"objective={objective}")
    cfg = load_train_config(config, overrides + ([f"training.device={device}"] if device else []))
    _start(device)
    ctx = DistContext.from_env()
    if not (resume or out):
        # the workspace's cached stage: remember the settings so that `sefa run` chains
        # (under torchrun too: the runner writes the same manifest as one process)
        from pipelines.stages import load_pipeline, save_pipeline

        if ctx.is_main:
            pipe = load_pipeline(workspace)
            pipe.train, pipe.train_config = overrides, str(config.resolve()) if config else None
            save_pipeline(workspace, pipe)
        _run_stages(workspace, ["train"], {"train"} if force else set(), as_json, device)
        return
    run_dir = out or workspace / "train"
    rank0 = ctx.is_main
    if force and run_dir.exists() and rank0:
        shutil.rmtree(run_dir)
    store = Path(cfg.dataset) if Path(cfg.dataset).is_absolute() else workspace / cfg.dataset
    with TrainProgress(enabled=rank0 and not as_json) as progress:
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


def _run_stages(workspace: Path, names: list[str] | None, force: set[str], as_json: bool,
                device: Optional[str] = None) -> None:
    from cli.console import TrainProgress
    from pipelines.stages import load_pipeline, run_stages
    from sefa_model.distributed import context

    _start(device)
    ctx = context()
    main_rank = ctx.is_main
    # rank 0's reading of sefa.yaml (which it may just have written) is every rank's
    pipe = ctx.broadcast(load_pipeline(workspace) if main_rank else None)
    with TrainProgress(enabled=not as_json and main_rank) as progress:
        results = run_stages(workspace, pipe, names, force,
                             log=progress.log, on_step=progress.on_step, device=device)
    if as_json and main_rank:
        print(json.dumps([{"stage": r.name, "ran": r.ran, "summary": r.manifest.get("summary")}
                          for r in results], indent=2, default=str))


def _workspace_device(workspace: Path) -> str:
    """`device` of the workspace's sefa.yaml, else auto."""
    from pipelines.stages import load_pipeline

    return load_pipeline(workspace).device or "auto"


def _update_pipeline(workspace: Path, section: str, **values) -> None:
    from pipelines.stages import load_pipeline, save_pipeline
    from sefa_model.distributed import context

    ctx = context()
    if not ctx.is_main:  # rank 0 writes sefa.yaml; the runner's broadcast orders the rest
        return
    pipe = load_pipeline(workspace)
    for key, value in values.items():
        if value is not None:
            setattr(getattr(pipe, section), key, value)
    save_pipeline(workspace, pipe)


@app.command()
def reflow(
    iters: Annotated[Optional[int], typer.Option(help="Reflow iterations (each its own cached artifact).")] = None,
    samples: Annotated[Optional[int], typer.Option(help="Noises per training window (K).")] = None,
    max_windows: Annotated[Optional[int], typer.Option(help="Use this many evenly spread training windows (quick runs).")] = None,
    align_rounds: Annotated[Optional[bool], typer.Option("--align-rounds/--no-align-rounds", help="Align each round's couplings (the align stage's eps) before the next round trains on them.")] = None,
    force: Annotated[bool, typer.Option(help="Rerun even if cached.")] = False,
    device: Device = None,
    workspace: Workspace = Path("."),
    as_json: JsonFlag = False,
) -> None:
    """Generate reflow couplings from the base flow (and train reflowed flows for --iters > 1)."""
    _update_pipeline(workspace, "reflow", iters=iters, samples_per_window=samples, max_windows=max_windows,
                     align_rounds=align_rounds)
    _run_stages(workspace, ["train", "reflow"], {"reflow"} if force else set(), as_json, device)


@app.command()
def align(
    eps: Annotated[Optional[float], typer.Option(help="Replace a generated chunk by the expert's when closer than this (normalized units).")] = None,
    matching_obs: Annotated[Optional[bool], typer.Option("--matching-obs/--same-window", help="Candidates from every window with a matching observation (the reference code's variant).")] = None,
    force: Annotated[bool, typer.Option(help="Rerun even if cached.")] = False,
    device: Device = None,
    workspace: Workspace = Path("."),
    as_json: JsonFlag = False,
) -> None:
    """Selective alignment of the last reflow couplings to the expert chunks."""
    variant = None if matching_obs is None else ("matching_obs" if matching_obs else "same_window")
    _update_pipeline(workspace, "align", eps=eps, variant=variant)
    _run_stages(workspace, ["train", "reflow", "align"], {"align"} if force else set(), as_json, device)
    from sefa_model.distributed import context

    if not as_json and context().is_main:
        from sefa_model.alignment import format_histogram

        summary = json.loads((workspace / "align" / "manifest.json").read_text())["summary"]
        print(f"replaced {summary['fraction_replaced']:.1%} of {summary['n']} couplings "
              f"(eps {summary['eps']:g}; {summary['metric']})")
        print(format_histogram(summary["histogram"], eps=summary["eps"]))


@app.command()
def distill(
    no_align: Annotated[bool, typer.Option("--no-align", help="Distil on the unaligned couplings (the plain reflow baseline).")] = False,
    force: Annotated[bool, typer.Option(help="Rerun even if cached.")] = False,
    device: Device = None,
    workspace: Workspace = Path("."),
    as_json: JsonFlag = False,
) -> None:
    """Train the one-step policy on the aligned couplings."""
    _update_pipeline(workspace, "distill", align=not no_align)
    _run_stages(workspace, ["train", "reflow", "align", "distill"] if not no_align
                else ["train", "reflow", "distill"], {"distill"} if force else set(), as_json, device)


@app.command()
def run(
    pipeline: Annotated[Optional[Path], typer.Argument(help="A pipeline YAML (default: WORKSPACE/sefa.yaml).")] = None,
    force: Annotated[list[str], typer.Option(help="Rerun this stage even if cached (repeatable).")] = [],
    device: Device = None,
    workspace: Workspace = Path("."),
    as_json: JsonFlag = False,
) -> None:
    """Run every stage in order; cached stages are skipped.

    On N GPUs: torchrun --nproc_per_node N -m cli.main run PIPELINE (the same manifests)."""
    from sefa_model.distributed import context

    if pipeline is not None and context().is_main:
        from pipelines.stages import load_pipeline, save_pipeline

        save_pipeline(workspace, load_pipeline(workspace, pipeline))
    _run_stages(workspace, None, set(force), as_json, device)


@app.command()
def status(workspace: Workspace = Path("."), as_json: JsonFlag = False) -> None:
    """Each stage of the workspace: cached, stale or missing, and why."""
    from pipelines.runner import Workspace as Ws, pipeline_status
    from pipelines.stages import load_pipeline, stages

    rows = pipeline_status(Ws(workspace), stages(workspace, load_pipeline(workspace)))
    if as_json:
        print(json.dumps([{"stage": n, "state": s, "reason": r} for n, s, r in rows], indent=2))
        return
    for name, state, reason in rows:
        print(f"{name:16s} {state:8s} {reason}")


@app.command(name="eval")
def eval_(
    checkpoints: Annotated[Optional[list[Path]], typer.Argument(help="Checkpoints or run dirs (default: every stage of the workspace).")] = None,
    offline: Annotated[bool, typer.Option("--offline", help="Validation action MSE and multimodality on the store (no simulator).")] = False,
    env: Annotated[Optional[str], typer.Option(help="Closed-loop rollouts in simulation: pusht or robosuite:Lift.")] = None,
    n_test: Annotated[int, typer.Option(help="Rollout episodes (test seeds from --start-seed).")] = 50,
    start_seed: Annotated[int, typer.Option(help="First test seed (Diffusion Policy: 100000).")] = 100000,
    max_steps: Annotated[int, typer.Option(help="Environment steps per rollout.")] = 300,
    solver: Annotated[Optional[str], typer.Option(help="Override the checkpoint's solver (flow: euler, midpoint, rk4, rk45, rk45-ps, dop853-ps; diffusion baseline: ddpm, ddim).")] = None,
    steps: Annotated[Optional[int], typer.Option(help="Steps for a fixed-step solver or the diffusion sampler.")] = None,
    windows: Annotated[int, typer.Option(help="Validation windows to evaluate.")] = 256,
    samples: Annotated[int, typer.Option(help="Samples per observation for the multimodality measure.")] = 8,
    out: Annotated[Optional[Path], typer.Option("--out", "-o", help="Rollouts: the folder for eval_log.json (one checkpoint; default: eval_<env>[_<solver>] beside it).")] = None,
    device: Device = None,
    workspace: Workspace = Path("."),
    as_json: JsonFlag = False,
) -> None:
    """Evaluate checkpoints: closed-loop rollouts (--env) or action MSE, NFE and sample spread on the store (--offline).

    Under torchrun the rollout seeds are split across the processes; rank 0 writes the log."""
    from rich.table import Table

    from cli.console import out as console_out
    from sefa_model.distributed import context
    from sefa_model.evaluate import evaluate_offline

    _start(device)
    device = device or _workspace_device(workspace)
    main_rank = context().is_main

    if env is None and not offline:
        raise SefaInputError("choose --offline (store-based metrics) or --env pusht (rollouts)")
    if env is not None and env not in ("pusht", "robosuite:Lift"):
        raise SefaInputError(f"unknown environment '{env}' (available: pusht, robosuite:Lift)",
                             key="--env")
    if not checkpoints:
        candidates = ["train", "reflow/iter_2/flow", "distill"]
        checkpoints = [workspace / c for c in candidates if (workspace / c / "checkpoints" / "latest").exists()]
        if not checkpoints:
            raise SefaInputError("no trained policy in this workspace (run `sefa train` first)",
                                 file=str(workspace))
    if out is not None and len(checkpoints) != 1:
        raise SefaInputError("--out takes one checkpoint", key="--out")
    if env is not None:
        from sefa_sim.rollouts import evaluate_lift, evaluate_pusht

        run_env = evaluate_pusht if env == "pusht" else evaluate_lift
        logs = []
        for c in checkpoints:
            setting = "" if solver is None else f"_{solver}" + ("" if steps is None else f"-{steps}")
            out_dir = out or (c if (c / "checkpoints").exists() else c.parent) / f"eval_{env.replace(':', '_')}{setting}"
            try:
                log = run_env(c, n_test=n_test, start_seed=start_seed, max_steps=max_steps,
                              solver=solver, steps=steps, out=out_dir, device=device)
            except ImportError as e:
                raise SefaInputError(f"the simulator for '{env}' is not installed ({e}); "
                                     "install sefa[sim]") from None
            if log is None:  # another rank's share: rank 0 reports
                continue
            logs.append({k: v for k, v in log.items() if k != "per_seed"} | {"eval_log": str(out_dir / "eval_log.json")})
        if not main_rank:
            return
        if as_json:
            print(json.dumps(logs, indent=2))
        else:
            for log in logs:
                print(f"{log['checkpoint']}: {log['kind']}, {log['solver']}: mean score "
                      f"{log['test/mean_score']:.3f}, success {log['test/success_rate']:.0%} over "
                      f"{log['n_test']} seeds from {log['test_start_seed']} ({log['eval_log']})")
        return
    if not main_rank:  # store metrics are one batched pass: rank 0 alone
        return
    rows = [evaluate_offline(c, workspace / "dataset.zarr", windows=windows, samples=samples,
                             solver=solver, steps=steps, device=device)
            for c in checkpoints]
    if as_json:
        print(json.dumps(rows, indent=2))
        return
    t = Table(title=f"offline evaluation ({rows[0]['split'] if rows else ''} windows)")
    for col in ("checkpoint", "kind", "solver", "NFE", "action MSE", "best-of-K MSE", "spread / expert"):
        t.add_column(col)
    for r in rows:
        t.add_row(r["checkpoint"], r["kind"], f"{r['solver']}{'' if r['steps'] is None else '-' + str(r['steps'])}",
                  str(r["nfe"]), f"{r['action_mse']:.4g}", f"{r['action_mse_best_of_k']:.4g}",
                  f"{r['spread']:.3f} / {r['expert_spread']:.3f}")
    console_out.print(t)


@app.command()
def collect(
    out: Annotated[Path, typer.Argument(help="The HDF5 file to write (robomimic layout).")],
    env: Annotated[str, typer.Option(help="robosuite:Lift (the scripted expert's task).")] = "robosuite:Lift",
    episodes: Annotated[int, typer.Option(help="Episodes to attempt; only successful ones are kept.")] = 100,
    seed: Annotated[int, typer.Option(help="Episode i resets with seed + i.")] = 0,
    cameras: Annotated[bool, typer.Option(help="Also record agentview and eye-in-hand images.")] = False,
    as_json: JsonFlag = False,
) -> None:
    """Record scripted expert demonstrations headless (no download)."""
    if env != "robosuite:Lift":
        raise SefaInputError(f"unknown environment '{env}' (available: robosuite:Lift)", key="--env")
    try:
        from sefa_sim.collect import collect_lift
    except ImportError as e:
        raise SefaInputError(f"the simulator is not installed ({e}); install sefa[sim]") from None
    summary = collect_lift(out, episodes, seed=seed, cameras=cameras)
    if as_json:
        print(json.dumps(summary, indent=2))
        return
    print(f"{out}: {summary['successful']}/{summary['attempted']} successful episodes kept "
          f"({summary['success_rate']:.0%}), {summary['steps']} steps")
    if summary["failed_seeds"]:  # dropped demos are said, not only counted
        print(f"not kept (the cube was not lifted within the step limit): seeds "
              f"{', '.join(map(str, summary['failed_seeds']))}", file=sys.stderr)


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
    except (KeyboardInterrupt, typer.Abort):
        print("interrupted: stores and artifacts are as they were before this stage",
              file=sys.stderr)
        if as_json:
            print(json.dumps({"error": {"message": "interrupted", "kind": "interrupted",
                                        "exit_code": 130}}))
        sys.exit(130)
    except OSError as e:  # EIO, a full disk, a file that vanished: the system's words, one line
        _error_exit(_os_error_line(e), as_json, kind="os")
    except MemoryError:
        _error_exit("out of memory (an input or a setting asks for more than this machine has)",
                    as_json, kind="memory")
    except Exception as e:
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


if __name__ == "__main__":
    main()
