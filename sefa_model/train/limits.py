"""The ranges that depend on the data and the machine: a batch is at most the windows (or
couplings) a training draws from, and what fits in the memory of the device it runs on.

Checked by the workspace before a command takes its lock (pipelines/stages.py:check_fits), so a
batch that cannot run is refused in one line instead of being killed by the kernel at 24 GB.
The memory figure is a deliberately low estimate (inputs and the main activations, fp32, not the
weights): a batch refused by it cannot fit; one that passes may still be too large.
"""

from __future__ import annotations

import copy
import math
import os
from pathlib import Path

from sefa_data.errors import ConfigError
from sefa_model.config import TrainConfig

FLOAT = 4  # bytes


def training_windows(cfg: TrainConfig, store_path: Path) -> int:
    """How many training windows this config draws from the store (what PolicyData's train
    split holds, the one-episode window split included)."""
    from sefa_data.sampler import SequenceSampler, window_split
    from sefa_data.store.zarr_store import EpisodeStore
    from sefa_model.policy.model import resolve_shapes

    store = EpisodeStore.open(store_path)
    cfg = resolve_shapes(copy.deepcopy(cfg), store)
    p = cfg.policy
    train = SequenceSampler(store, split="train", horizon=p.horizon, n_obs_steps=p.n_obs_steps,
                            n_action_steps=p.n_action_steps, obs_keys=list(cfg.shape_meta.obs),
                            action_key=cfg.shape_meta.action.key)
    n = len(train)
    if not store.mask("valid").any() and n > p.horizon:
        n = len(window_split(n, p.horizon)[0])
    return n


def bytes_per_sample(cfg: TrainConfig) -> int:
    """A low estimate of one training sample's memory: the observation frames and action chunk
    as tensors, the image encoders' first feature maps (unless frozen), the head's activations;
    forward and backward. `cfg` has its shapes resolved."""
    p, meta = cfg.policy, cfg.shape_meta
    total = 0
    for spec in meta.obs.values():
        frame = math.prod(spec.shape or [1])
        total += p.n_obs_steps * frame * FLOAT * 2  # the host batch and its device copy
        if spec.type == "rgb" and not cfg.training.freeze_encoder:
            c, h, w = spec.shape
            if p.crop_shape:
                h, w = p.crop_shape
            # the first stage's maps (32 channels at half resolution, a few tensors kept for
            # backward) are far below what the whole encoder keeps: a floor, not a forecast
            total += p.n_obs_steps * (h // 2) * (w // 2) * 32 * FLOAT * 4
    action = math.prod(meta.action.shape or [1])
    total += p.horizon * action * FLOAT * 4  # noise, target, x_t, prediction
    if p.head == "unet":
        # each level's two residual blocks (conv, norm, activation) down and up
        total += p.horizon * sum(p.down_dims) * FLOAT * 2 * 6
    else:
        total += sum(p.mlp_hidden_dims) * FLOAT * 4
    return total * 2  # activations and their gradients


def available_memory(device: str) -> tuple[int | None, str]:
    """(bytes free on `device`, what that is in words); None when it cannot be told."""
    from sefa_model.distributed import resolve_device

    try:
        dev = resolve_device(device)
    except Exception:  # the stage reports a bad device itself
        return None, device
    if dev.type == "cuda":
        import torch

        free, _ = torch.cuda.mem_get_info(dev)
        return int(free), f"{dev} has {_gib(free)} free"
    free = _mem_available()
    if free is None:
        return None, "host"
    return free, f"this machine has {_gib(free)} of memory available"


def _mem_available() -> int | None:
    """The kernel's MemAvailable (free pages and the page cache it can drop), else free pages."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return None


def _gib(n: float) -> str:
    return f"{n / 2 ** 30:.1f} GiB" if n >= 2 ** 30 else f"{n / 2 ** 20:.0f} MiB"


def check_batch(cfg: TrainConfig, store_path: Path, *, draws: int | None = None,
                what: str = "training windows", key: str = "training.batch_size",
                world: int = 1) -> None:
    """Refuse a batch larger than the items it draws from (`draws`, default the store's
    training windows) or than the device's free memory, naming `key` and the valid range."""
    from sefa_data.store.zarr_store import EpisodeStore
    from sefa_model.policy.model import resolve_shapes

    batch = cfg.training.batch_size
    n = training_windows(cfg, store_path) if draws is None else draws
    if batch > n:
        raise ConfigError(f"{batch} is more than the {n} {what} it draws from (valid: an integer "
                          f"in [1, {n}])", key=key)
    resolved = resolve_shapes(copy.deepcopy(cfg), EpisodeStore.open(store_path))
    per = bytes_per_sample(resolved)
    free, where = available_memory(cfg.training.device)
    local = math.ceil(batch / max(world, 1))
    if free is not None and per > free:  # not the batch: a single sample is too large
        _one_sample_too_large(resolved, per, where)
    if free is not None and local * per > free:
        fits = max(1, free // per) * max(world, 1)
        raise ConfigError(f"{batch} samples need at least {_gib(local * per)} per process "
                          f"(about {per / 2 ** 10:.0f} KiB per sample: inputs and activations, a "
                          f"low estimate) but {where} (valid: an integer in [1, "
                          f"{min(n, fits)}])", key=key)


def _one_sample_too_large(cfg: TrainConfig, per: int, where: str) -> None:
    """A sample that alone exceeds the memory: the largest camera's model size is what to
    change (a batch of 1 would not fit either); without cameras, the model's shapes."""
    cameras = {k: s.shape for k, s in cfg.shape_meta.obs.items() if s.type == "rgb"}
    if cameras:
        key = max(cameras, key=lambda k: math.prod(cameras[k]))
        _, h, w = cameras[key]
        raise ConfigError(f"one training sample with camera '{key}' at {h}x{w} needs at least "
                          f"{_gib(per)} but {where}: choose a smaller model size (e.g. "
                          f"shape_meta.obs.{key}.resize=[96,96])",
                          key=f"shape_meta.obs.{key}.resize")
    raise ConfigError(f"one training sample needs at least {_gib(per)} (horizon "
                      f"{cfg.policy.horizon}, inputs and activations) but {where}",
                      key="policy.horizon")
