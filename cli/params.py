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
        import torch

        torch.set_num_threads(threads)


def workspace_device(workspace: Path) -> str:
    """`device` of the workspace's sefa.yaml, else auto."""
    from sefa_pipelines.stages import load_pipeline

    return load_pipeline(workspace).device or "auto"
