"""Devices and processes: the one place that picks a device and joins torchrun's process group.

Every stage (train, reflow, align, distill, eval, bench, run, serve) takes `--device
auto|cpu|cuda|cuda:N|mps` and resolves it here. Under `torchrun` (RANK, WORLD_SIZE, LOCAL_RANK
in the environment) each process takes the GPU of its LOCAL_RANK *before* the process group
starts, and NCCL is told that device (`device_id`), so barriers and collectives never land on
cuda:0 from every rank. The process group is PyTorch's own (`torch.distributed`), started once
per process and closed at exit; nothing here manages processes.

Random draws that must not depend on the device (noise of a coupling, of a rollout step) are
made on the CPU by a CPU `torch.Generator` and then copied: the same seed gives bit-identical
noise on a CPU, a GPU or any number of ranks.
"""

from __future__ import annotations

import atexit
import os
import re
from dataclasses import dataclass
from typing import Any, Sequence, TypeVar

import numpy as np
import torch
import torch.distributed as torch_dist

from sefa_data.errors import SefaInputError

T = TypeVar("T")
DEVICE_HELP = "auto, cpu, cuda, cuda:N or mps"
_DEVICE_RE = re.compile(r"^(auto|cpu|mps|cuda(:\d+)?)$")


@dataclass(frozen=True)
class DistContext:
    """This process's place among torchrun's processes (one process: rank 0 of 1)."""

    rank: int = 0
    world: int = 1
    local_rank: int = 0
    local_world: int = 1

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        return self.world > 1

    @classmethod
    def from_env(cls) -> "DistContext":
        """torchrun sets RANK, WORLD_SIZE, LOCAL_RANK and LOCAL_WORLD_SIZE."""
        if "RANK" not in os.environ or "WORLD_SIZE" not in os.environ:
            return cls()
        return cls(int(os.environ["RANK"]), int(os.environ["WORLD_SIZE"]),
                   int(os.environ.get("LOCAL_RANK", 0)),
                   int(os.environ.get("LOCAL_WORLD_SIZE", os.environ["WORLD_SIZE"])))

    # --- collectives: no-ops (identity) in a single process ----------------------------------

    def barrier(self) -> None:
        if self.distributed:
            torch_dist.barrier()

    def broadcast(self, value: T, src: int = 0) -> T:
        """Rank `src`'s Python object on every rank."""
        if not self.distributed:
            return value
        box = [value if self.rank == src else None]
        torch_dist.broadcast_object_list(box, src=src)
        return box[0]

    def gather(self, value: T) -> list[T] | None:
        """Every rank's object, in rank order, on rank 0 (None elsewhere)."""
        if not self.distributed:
            return [value]
        out: list[Any] | None = [None] * self.world if self.is_main else None
        torch_dist.gather_object(value, out, dst=0)
        return out

    def mean(self, value: torch.Tensor) -> torch.Tensor:
        """The mean over ranks of a scalar tensor (a collective: every rank must call it)."""
        if not self.distributed:
            return value
        value = value.detach().clone()
        torch_dist.all_reduce(value)
        return value / self.world

    def shard(self, items: Sequence[T] | np.ndarray) -> Sequence[T] | np.ndarray:
        """This rank's share of `items` (round-robin: item i goes to rank i % world)."""
        return items[self.rank::self.world]


def context() -> DistContext:
    return DistContext.from_env()


def check_device_name(name: str, key: str = "--device") -> str:
    name = str(name).strip()
    if not _DEVICE_RE.match(name):
        raise SefaInputError(f"unknown device '{name}' (valid: {DEVICE_HELP})", key=key)
    return name


def resolve_device(name: str | torch.device | None = "auto", ctx: DistContext | None = None,
                   key: str = "--device") -> torch.device:
    """The torch.device for `name`. `auto` takes CUDA, then MPS, then the CPU; under torchrun a
    bare `cuda` (or `auto`) means the GPU of this process's LOCAL_RANK."""
    if isinstance(name, torch.device):
        return name
    ctx = ctx or context()
    name = check_device_name(name or "auto", key)
    if name == "auto":
        if torch.cuda.is_available():
            name = "cuda"
        elif getattr(torch.backends, "mps", None) and torch.backends.mps.is_available():
            return torch.device("mps")
        else:
            return torch.device("cpu")
    device = torch.device(name)
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise SefaInputError(f"device '{name}' asked for, but CUDA is not available on this "
                                 f"machine (use --device cpu or auto)", key=key)
        if device.index is None:
            device = torch.device("cuda", ctx.local_rank if ctx.distributed else torch.cuda.current_device())
        if device.index >= torch.cuda.device_count():
            raise SefaInputError(f"device '{name}' asked for, but this machine has "
                                 f"{torch.cuda.device_count()} GPU(s)", key=key)
    if device.type == "mps" and not (getattr(torch.backends, "mps", None)
                                     and torch.backends.mps.is_available()):
        raise SefaInputError(f"device '{name}' asked for, but MPS is not available", key=key)
    return device


def setup(device: str | torch.device | None = "auto", key: str = "--device"
          ) -> tuple[DistContext, torch.device]:
    """Pick this process's device and, under torchrun, join the process group (once).

    The order matters: `torch.cuda.set_device` before `init_process_group`, and `device_id` for
    NCCL, so that each rank's communicator and barriers use its own GPU."""
    ctx = context()
    dev = resolve_device(device, ctx, key)
    if dev.type == "cuda":
        torch.cuda.set_device(dev)
        enable_fast_matmul()
    if ctx.distributed and not torch_dist.is_initialized():
        if dev.type == "cuda":
            torch_dist.init_process_group("nccl", device_id=dev)
        else:
            torch_dist.init_process_group("gloo")
        atexit.register(_close)
    return ctx, dev


def ensure_process_group(device: str = "auto") -> DistContext:
    """Under torchrun, the process group on `device` unless one is already started."""
    ctx = context()
    if ctx.distributed and not torch_dist.is_initialized():
        setup(device)
    return ctx


def enable_fast_matmul() -> None:
    """TF32 tensor cores for float32 matmuls and convolutions (Ampere and newer): about 8x the
    float32 rate at a 10-bit mantissa, which training and sampling tolerate (PyTorch's own
    recommendation for training)."""
    torch.backends.cuda.matmul.allow_tf32 = True
    torch.backends.cudnn.allow_tf32 = True


def bf16_supported(device: torch.device) -> bool:
    return device.type == "cuda" and torch.cuda.is_bf16_supported()


def _close() -> None:
    if torch_dist.is_available() and torch_dist.is_initialized():
        torch_dist.destroy_process_group()


def describe(device: torch.device) -> str:
    """A device as logs print it: `cuda:0 (NVIDIA H100 80GB HBM3)`, `cpu (2 threads)`."""
    if device.type == "cuda":
        return f"{device} ({torch.cuda.get_device_name(device)})"
    if device.type == "cpu":
        return f"cpu ({torch.get_num_threads()} threads)"
    return str(device)


def busy_cpu_note(device: torch.device, threads: int, load: float | None,
                  cores: int | None) -> str | None:
    """A line when a CPU run's threads compete with other work: on a busy 2-core machine torch's
    2 threads ran 0.5 steps/s where `--threads 1` ran 12 (issue 25), so it is said when seen,
    not only in --help. `load`: the 1-minute load average, this process not yet counted."""
    if device.type != "cpu" or threads <= 1 or load is None or not cores or load < cores:
        return None
    return (f"the machine is busy (load {load:.1f} on {cores} cores) and torch uses {threads} "
            f"threads: `--threads 1` (or `threads: 1` in sefa.yaml) is often much faster here")


_threads_given = False  # whether the user chose torch's CPU threads (set_threads)


def set_threads(n: int) -> None:
    """torch's CPU threads as the user chose them (--threads, sefa.yaml's `threads`): a
    training then keeps them rather than measuring (sefa_model/train/threads.py)."""
    global _threads_given
    torch.set_num_threads(n)
    _threads_given = True


def threads_given() -> bool:
    """Whether the thread count was chosen: by set_threads, or by OMP_NUM_THREADS, which
    sets torch's default."""
    return _threads_given or bool(os.environ.get("OMP_NUM_THREADS"))


def load_average() -> float | None:
    try:
        return os.getloadavg()[0]
    except (AttributeError, OSError):  # Windows has none
        return None


def cpu_noise(shape: Sequence[int], generator: torch.Generator | None, device: torch.device
              ) -> torch.Tensor:
    """Standard normal noise drawn where the generator lives (the CPU by default) and copied
    to `device`: with a CPU generator the values are the same on every device."""
    where = generator.device if generator is not None else torch.device("cpu")
    x = torch.randn(tuple(shape), generator=generator, device=where)
    return x.to(device, non_blocking=True) if x.device != device else x
