"""The options several commands share (-w, --json, --device, --threads) and what --device and
--threads set up before a command's work."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

Workspace = Annotated[Path, typer.Option("--workspace", "-w", help="Workspace directory.")]
JsonFlag = Annotated[bool, typer.Option("--json", is_flag=True, show_default=False, metavar="", help="Print a JSON summary on stdout.")]
Device = Annotated[Optional[str], typer.Option(
    help="auto, cpu, cuda, cuda:N or mps (default: `device` in sefa.yaml, else auto). Under "
         "torchrun, cuda means each process's LOCAL_RANK GPU.")]
Threads = Annotated[Optional[int], typer.Option(
    "--threads", min=1,
    help="CPU threads for torch (default: `threads` in sefa.yaml, else torch's own choice). On a "
         "busy machine 1 is often much faster.")]


def start_process(device: Optional[str], threads: Optional[int] = None,
                  workspace: Optional[Path] = None, pipeline: Optional[Path] = None) -> None:
    """Under torchrun: join the process group on the chosen device before anything else."""
    from sefa_model.distributed import ensure_process_group, resolve_device

    if device is not None:
        resolve_device(device)  # an unknown or absent device stops the command before any work
    set_threads(threads, workspace, pipeline)
    ensure_process_group(device or "auto")


def set_threads(threads: Optional[int], workspace: Optional[Path],
                 pipeline: Optional[Path] = None) -> None:
    """`threads` of the settings the command runs with: PIPELINE's for `sefa run PIPELINE`."""
    if threads is None and workspace is not None and (
            pipeline is not None or (workspace / "sefa.yaml").exists()):
        from sefa_pipelines.stages import load_pipeline

        threads = load_pipeline(workspace, pipeline).threads
    if threads is not None:
        from sefa_model.distributed import set_threads as use

        use(threads)


def workspace_device(workspace: Path) -> str:
    """`device` of the workspace's sefa.yaml, else auto."""
    from sefa_pipelines.stages import load_pipeline

    return load_pipeline(workspace).device or "auto"


# how chunks become one action per step (sefa eval --env, sefa serve, sefa choose-execution);
# none given: the execution recorded with the policy (sefa choose-execution), else receding
# horizon over n_action_steps
Execution = Annotated[Optional[str], typer.Option(
    "--execution",
    help="How chunks become one action per step: receding (execute --replan-every actions, then "
         "predict; Diffusion Policy), ensemble (predict every --replan-every steps, execute the "
         "exp(-k i)-weighted mean of the predictions for the step; ACT), coherent (draw --samples "
         "chunks in one batched call, keep the one nearest the previous plan), bid (Bidirectional "
         "Decoding: coherence, then contrast against --weak). Default: the execution chosen for "
         "the policy (sefa choose-execution), else receding. Any execution option given replaces "
         "that one as a whole: --replan-every 2 alone is receding every 2 steps.")]
ReplanEvery = Annotated[Optional[int], typer.Option(
    "--replan-every", help="Steps between predictions, 1..n_action_steps [default: n_action_steps for receding, 1 for the others].")]
Samples = Annotated[Optional[int], typer.Option(
    "--samples", help="coherent, bid: chunks drawn per decision in one batched call [default: 16].")]
Decay = Annotated[Optional[float], typer.Option(
    "--decay", help="coherent, bid: backward coherence's weight decay per step, in (0, 1] [default: 0.9].")]
EnsembleK = Annotated[Optional[float], typer.Option(
    "--ensemble-k", help="ensemble: ACT's k (>= 0), weight exp(-k i), i = 0 the oldest prediction [default: 0.01, ACT's].")]
Weak = Annotated[Optional[str], typer.Option(
    "--weak", help="bid: the weaker policy, CHECKPOINT[@SOLVER-STEPS] (e.g. train@euler-1: the base flow at one Euler step).")]
