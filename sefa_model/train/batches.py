"""What each optimizer step fits, and how its batch is drawn.

Every random draw of step k (the batch's windows, the noise, t, crops) is derived from
(seed, k) alone. A resumed run therefore replays exactly what an uninterrupted one does, and a
DDP run with N ranks draws the same global batch as a single process and gives each rank its
slice of it.

    pairs = ExpertPairs(data)                      # the base flow (or the diffusion baseline)
    pairs = CouplingPairs(data, PairSource(...))   # a reflowed flow or the one-step student
    for batch in step_batches(pairs, cfg, first_step, mine, device, workers):
        obs, x0, x1, times = pairs.to_device(batch, device)
"""

from __future__ import annotations

import math
import os
from typing import Callable

import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset

from sefa_data.errors import SefaInputError
from sefa_model.config import TrainConfig
from sefa_model.data.couplings import PairSource, read_pairs
from sefa_model.distributed import DistContext
from sefa_model.data.windows import PolicyData
from sefa_model.methods import Times, get, method_of

# ----------------------------------------------------------------------------- pure helpers


def cosine_with_warmup(warmup: int, total: int) -> Callable[[int], float]:
    """LR multiplier: linear warm-up, then a cosine decay to zero (diffusers' schedule)."""
    def factor(step: int) -> float:
        if step < warmup:
            return step / max(1, warmup)
        progress = (step - warmup) / max(1, total - warmup)
        return max(0.0, 0.5 * (1 + math.cos(math.pi * min(1.0, progress))))
    return factor


def batch_indices(seed: int, step: int, n_windows: int, batch: int) -> np.ndarray:
    """The global batch of step `step`: epochs are seeded permutations, the last partial batch
    of an epoch is dropped (DP's loader), and a dataset smaller than a batch is tiled."""
    epoch, offset = divmod(step, max(1, n_windows // batch))
    return epoch_order(seed, epoch, n_windows, batch)[offset * batch:(offset + 1) * batch]


def epoch_order(seed: int, epoch: int, n_windows: int, batch: int) -> np.ndarray:
    """The windows of epoch `epoch` in the order its steps take them (batch_indices' slices;
    sefa_model/train/device_batches.py keeps one epoch's order on the device)."""
    perm = np.random.default_rng([seed, epoch]).permutation(n_windows)
    return np.resize(perm, batch) if n_windows < batch else perm


def step_seed(seed: int, step: int, salt: int = 0) -> int:
    """An independent seed per (run seed, step, purpose)."""
    return int(np.random.SeedSequence([seed, step, salt]).generate_state(1)[0])


def step_generator(seed: int, step: int, salt: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(step_seed(seed, step, salt))


def epoch_of(step: int, n_windows: int, batch: int) -> int:
    return step // max(1, n_windows // batch)


def yardstick(cfg: TrainConfig):
    """The method whose loss validation reports for every policy of one family: the flow
    matching loss at t ~ U[t_eps, 1] for any flow policy (students included, so that their
    numbers compare), the diffusion baseline's own."""
    return get(method_of(cfg).yardstick)


# ----------------------------------------------------------------------------- what a step fits


def _times(times: Times, mine: slice) -> dict:
    """This rank's slice of a global batch's training times, as batch entries."""
    out = {"t": times.t[mine]}
    if times.d is not None:
        out["d"] = times.d[mine]
    return out


def _device_times(batch: dict, device: torch.device) -> Times:
    d = batch.get("d")
    return Times(batch["t"].to(device, non_blocking=True),
                 None if d is None else d.to(device, non_blocking=True))


class ExpertPairs:
    """Expert windows with fresh noise for every window at every step, the expert chunk as x1,
    and the method's training times: the base flow (t ~ U[t_eps, 1]), the diffusion baseline
    (an integer timestep k), and the students that distil the base flow on fresh noise (mean
    flow, shortcut). After `use_features` (a student's frozen encoder), a batch carries each
    window's condition instead of its observation."""

    def __init__(self, data: PolicyData):
        self.data = data
        self.method = method_of(data.cfg)
        self.kind = self.method.kind()
        self.features: torch.Tensor | None = None  # (n_train_windows, D)

    def __len__(self) -> int:
        return len(self.data.train)

    def windows(self) -> np.ndarray:
        return np.arange(len(self.data.train))

    def use_features(self, features: torch.Tensor) -> None:
        """`features[i]` is the condition of training window i."""
        self.features = features

    def fetch(self, idx: np.ndarray, gen: torch.Generator, mine: slice) -> dict:
        """This rank's share of a global batch, on the host. The noise and t of the WHOLE
        global batch are drawn, so that every rank's slice is the one a single process draws."""
        cfg = self.data.cfg
        x0 = torch.randn(len(idx), cfg.policy.horizon, cfg.shape_meta.action.shape[-1], generator=gen)
        batch = {"x0": x0[mine], **_times(self.method.draw(cfg, len(idx), gen), mine)}
        if self.features is not None:
            sel = idx[mine]
            batch["cond"] = self.features[sel]
            batch["action"] = torch.from_numpy(np.ascontiguousarray(self.data.train.actions(sel)))
        else:
            batch["obs"] = self.data.host_batch(self.data.train, idx[mine])
        return batch

    def to_device(self, batch: dict, device: torch.device):
        if "cond" in batch:
            inputs, raw = batch["cond"].to(device, non_blocking=True), batch["action"]
        else:
            inputs, raw = self.data.device_obs(batch["obs"], device), batch["obs"][
                self.data.cfg.shape_meta.action.key]
        x1 = raw.to(device, non_blocking=True).float()
        return (inputs, batch["x0"].to(device, non_blocking=True), self.data.normalize_actions(x1),
                _device_times(batch, device))


class CouplingPairs:
    """Reflow and distillation: stored (noise, target) couplings of training windows.

    The training times are the method's (sefa_model/methods): a reflowed flow's t ~ U[t_eps, 1],
    the reference student's t = t_eps only (one Euler step from the noise lands on the
    target) or the k times k Euler steps visit, 2-RF++'s U-shaped t. After `use_features`, a
    batch carries each window's frozen condition instead of its observation.
    """

    def __init__(self, data: PolicyData, source: PairSource):
        self.method = method_of(data.cfg)
        if not self.method.solves_ode:
            raise SefaInputError(f"couplings train a flow, but the config's method is "
                                 f"'{self.method.name}'", key="method")
        c = read_pairs(source, data.provenance(), len(data.train))
        self.noise, self.target, self.window = c.noise, c.action, c.window
        self.data, self.kind = data, source.kind
        self.features: torch.Tensor | None = None  # (n_windows_used, D), rows by feature_row
        self.feature_row: np.ndarray | None = None  # training window -> row of `features`

    def __len__(self) -> int:
        return len(self.noise)

    def windows(self) -> np.ndarray:
        """The distinct training windows the couplings use, sorted."""
        return np.unique(self.window)

    def use_features(self, features: torch.Tensor) -> None:
        """`features[i]` is the condition of training window `self.windows()[i]`."""
        windows = self.windows()
        self.feature_row = np.full(int(windows[-1]) + 1 if len(windows) else 0, -1, np.int64)
        self.feature_row[windows] = np.arange(len(windows))
        self.features = features

    def fetch(self, idx: np.ndarray, gen: torch.Generator, mine: slice) -> dict:
        times = _times(self.method.draw(self.data.cfg, len(idx), gen), mine)
        sel = idx[mine]
        batch = {"x0": torch.from_numpy(self.noise[sel]), "x1": torch.from_numpy(self.target[sel]),
                 **times}
        if self.features is not None:
            batch["cond"] = self.features[self.feature_row[self.window[sel]]]
        else:
            batch["obs"] = self.data.host_batch(self.data.train, self.window[sel])
        return batch

    def to_device(self, batch: dict, device: torch.device):
        inputs = (batch["cond"].to(device, non_blocking=True) if "cond" in batch
                  else self.data.device_obs(batch["obs"], device))
        return (inputs, batch["x0"].to(device, non_blocking=True),
                batch["x1"].to(device, non_blocking=True), _device_times(batch, device))


class StepBatches(Dataset):
    """Item `step` is this rank's batch of that optimizer step, built on the host. Each step's
    draw depends on (seed, step) alone, so loader workers may build steps in any order and
    DataLoader still hands them out in step order: the run is the same with 0 or 8 workers."""

    def __init__(self, pairs, seed: int, batch_size: int, mine: slice):
        self.pairs, self.seed, self.batch_size, self.mine = pairs, seed, batch_size, mine

    def __len__(self) -> int:  # steps are addressed directly; the sampler bounds them
        return 2 ** 62

    def __getitem__(self, step: int) -> dict:
        idx = batch_indices(self.seed, step, len(self.pairs), self.batch_size)
        return self.pairs.fetch(idx, step_generator(self.seed, step), self.mine)


def loader_workers(setting: int | None, device: torch.device, ctx: DistContext) -> int:
    """`training.num_workers`, or by default: none on the CPU (the step already uses every
    core, and a worker only competes with it), else the cores of this rank minus its own."""
    if setting is not None:
        return setting
    if device.type == "cpu":
        return 0
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return max(1, min(8, cores // max(1, ctx.local_world) - 1))


def step_batches(pairs, cfg: TrainConfig, first_step: int, mine: slice, device: torch.device,
                 workers: int) -> DataLoader:
    """Batches of steps first_step.. max_steps - 1, prepared ahead by `workers` processes
    (image decoding included) and pinned for asynchronous copies when training on a GPU."""
    t_cfg = cfg.training
    return DataLoader(StepBatches(pairs, t_cfg.seed, t_cfg.batch_size, mine), batch_size=None,
                      sampler=range(first_step, t_cfg.max_steps), num_workers=workers,
                      pin_memory=device.type == "cuda", prefetch_factor=4 if workers else None)
