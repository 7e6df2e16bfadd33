"""What each optimizer step fits, and how its batch is drawn.

Every random draw of step k (the batch's windows, the noise, t, crops) is derived from
(seed, k) alone. A resumed run therefore replays exactly what an uninterrupted one does, and a
DDP run with N ranks draws the same global batch as a single process and gives each rank its
slice of it.

    pairs = ExpertPairs(data)                      # the base flow (or the diffusion baseline)
    pairs = CouplingPairs(data, PairSource(...))   # a reflowed flow or the one-step student
    for batch in step_batches(pairs, cfg, first_step, mine, device, workers):
        obs, x0, x1, t = pairs.to_device(batch, device)
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
from sefa_model.couplings import PairSource, read_pairs
from sefa_model.diffusion import ddpm_loss, make_scheduler, sample_timesteps
from sefa_model.distributed import DistContext
from sefa_model.policy_data import PolicyData
from sefa_model.rectified_flow import euler_grid_t, flow_loss, sample_t

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
    per_epoch = max(1, n_windows // batch)
    epoch, offset = divmod(step, per_epoch)
    perm = np.random.default_rng([seed, epoch]).permutation(n_windows)
    if n_windows < batch:
        perm = np.resize(perm, batch)
    return perm[offset * batch:(offset + 1) * batch]


def step_seed(seed: int, step: int, salt: int = 0) -> int:
    """An independent seed per (run seed, step, purpose)."""
    return int(np.random.SeedSequence([seed, step, salt]).generate_state(1)[0])


def step_generator(seed: int, step: int, salt: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(step_seed(seed, step, salt))


def epoch_of(step: int, n_windows: int, batch: int) -> int:
    return step // max(1, n_windows // batch)


def draw_time(cfg: TrainConfig, batch: int, gen: torch.Generator) -> torch.Tensor:
    """The objective's training time per sample: flow t ~ U[t_eps, 1], or a diffusion step k."""
    if cfg.objective == "ddpm":
        return sample_timesteps(batch, cfg.diffusion.num_train_timesteps, gen)
    return sample_t(batch, cfg.flow.t_eps, gen)


def objective_loss(cfg: TrainConfig) -> Callable:
    """loss(model_fn(x, t), noise x0, chunk x1, t) of the configured objective."""
    if cfg.objective == "ddpm":
        scheduler = make_scheduler(cfg.diffusion)
        return lambda f, x0, x1, t: ddpm_loss(f, x0, x1, t, scheduler)
    return flow_loss


# ----------------------------------------------------------------------------- what a step fits


class ExpertPairs:
    """Base flow: fresh noise for every window, the expert chunk as x1, t ~ U[t_eps, 1].
    The diffusion baseline draws the same noise and an integer timestep k instead of t."""

    def __init__(self, data: PolicyData):
        self.data = data
        self.kind = "ddpm" if data.cfg.objective == "ddpm" else "base_flow"

    def __len__(self) -> int:
        return len(self.data.train)

    def fetch(self, idx: np.ndarray, gen: torch.Generator, mine: slice) -> dict:
        """This rank's share of a global batch, on the host. The noise and t of the WHOLE
        global batch are drawn, so that every rank's slice is the one a single process draws."""
        cfg = self.data.cfg
        x0 = torch.randn(len(idx), cfg.policy.horizon, cfg.shape_meta.action.shape[-1], generator=gen)
        t = draw_time(cfg, len(idx), gen)
        return {"obs": self.data.host_batch(self.data.train, idx[mine]), "x0": x0[mine],
                "t": t[mine]}

    def to_device(self, batch: dict, device: torch.device):
        key = self.data.cfg.shape_meta.action.key
        x1 = batch["obs"][key].to(device, non_blocking=True).float()
        return (self.data.device_obs(batch["obs"], device), batch["x0"].to(device, non_blocking=True),
                self.data.normalize_actions(x1), batch["t"].to(device, non_blocking=True))


class CouplingPairs:
    """Reflow and distillation: stored (noise, target) couplings of training windows.

    The training time is the config's `flow.t_train`: "uniform" trains a reflowed flow on them
    (t ~ U[t_eps, 1]); "start" trains the velocity at t = t_eps only, so that one Euler step
    from the noise lands on the target; "grid" at the k times k Euler steps visit. After `use_features`, a batch carries each window's
    frozen condition instead of its observation.
    """

    def __init__(self, data: PolicyData, source: PairSource):
        if data.cfg.objective != "flow":
            raise SefaInputError(f"couplings train a flow, but the config's objective is "
                                 f"'{data.cfg.objective}'", key="objective")
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
        flow = self.data.cfg.flow
        if flow.t_train == "uniform":
            t = sample_t(len(idx), flow.t_eps, gen)[mine]
        elif flow.t_train == "grid":
            t = euler_grid_t(len(idx), flow.t_eps, flow.steps, gen)[mine]
        else:
            t = torch.full((len(idx),), float(flow.t_eps))[mine]
        sel = idx[mine]
        batch = {"x0": torch.from_numpy(self.noise[sel]), "x1": torch.from_numpy(self.target[sel]),
                 "t": t}
        if self.features is not None:
            batch["cond"] = self.features[self.feature_row[self.window[sel]]]
        else:
            batch["obs"] = self.data.host_batch(self.data.train, self.window[sel])
        return batch

    def to_device(self, batch: dict, device: torch.device):
        inputs = (batch["cond"].to(device, non_blocking=True) if "cond" in batch
                  else self.data.device_obs(batch["obs"], device))
        return (inputs, batch["x0"].to(device, non_blocking=True),
                batch["x1"].to(device, non_blocking=True), batch["t"].to(device, non_blocking=True))


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
