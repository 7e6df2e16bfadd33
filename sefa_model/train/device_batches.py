"""Training batches gathered where the model trains: the data lives on the device, each step's
windows are gathered there by index, and only the step's noise and t cross from the host.

On a GPU the loader's way (train_batches.StepBatches: each step's windows gathered from numpy
on the host, pinned, copied, in worker processes) costs more host time per step than a small
network's whole step; here the low-dim store (or a frozen encoder's features, or couplings) and
images as uint8 are copied to the device once, with the training windows' frame table, and a
step is a few gathers.

The draws are StepBatches' own, so a batch is bit for bit the loader's batch (on the same
device; tests/sefa_model_tests/test_device_batches.py) and a resumed run replays an uninterrupted one:

- the windows: train_batches.epoch_order, the order batch_indices slices, kept on the device
  for the current epoch (one upload per epoch instead of a permutation per step);
- the noise and the method's times (sefa_model/methods): drawn on the CPU by
  step_generator(seed, step), in the loader's order, then copied (pinned, asynchronously on CUDA). Drawing them on the device would save a copy
  of a few kilobytes but change every run's numbers.

`resident_batches` is the one switch (training.py): on CUDA when everything fits in a share
of the free device memory, else None and the loader runs as before. The CPU keeps the loader
(it is as fast there, and a CPU run's numbers must not move); tests force this path on the CPU.
"""

from __future__ import annotations

from typing import Iterator

import numpy as np
import torch

from sefa_model.config import TrainConfig
# _times: a draw's batch entries, as the loader's fetch makes them (one owner)
from sefa_model.train.batches import (CouplingPairs, ExpertPairs, _times, epoch_order,
                                      step_generator)

# the share of the free device memory the data may take: the rest is the model's, its
# optimizer's and the activations' (a U-Net at batch 256 needs a few GiB)
MEMORY_SHARE = 0.5
# tests set this to run the device path on the CPU
FORCE = False


def resident_batches(pairs: ExpertPairs | CouplingPairs, cfg: TrainConfig, first_step: int,
                     mine: slice, device: torch.device) -> Iterator[dict] | None:
    """The batches of steps first_step .. max_steps - 1 gathered on `device`, or None where the
    loader should build them: not on CUDA (unless FORCE), or the data would not fit."""
    if not (FORCE or device.type == "cuda"):
        return None
    if device.type == "cuda":
        free, _ = torch.cuda.mem_get_info(device)
        if resident_bytes(pairs) > MEMORY_SHARE * free:
            return None
    t_cfg = cfg.training
    batches = DeviceBatches(pairs, t_cfg.seed, t_cfg.batch_size, mine, device)
    return (batches[step] for step in range(first_step, t_cfg.max_steps))


def resident_bytes(pairs: ExpertPairs | CouplingPairs) -> int:
    """What DeviceBatches copies to the device, in bytes."""
    sampler = pairs.data.train
    total = sum(sampler.buffer_nbytes(k) for k in _keys(pairs))
    if _keys(pairs):
        total += len(sampler) * sampler.horizon * 8  # the frame table, int64
    if isinstance(pairs, CouplingPairs):
        total += pairs.noise.nbytes + pairs.target.nbytes + pairs.window.nbytes
        if pairs.feature_row is not None:
            total += pairs.feature_row.nbytes
    if pairs.features is not None:
        total += pairs.features.numel() * pairs.features.element_size()
    return total


def _keys(pairs: ExpertPairs | CouplingPairs) -> list[str]:
    """The store keys a batch gathers, in sampler.batch's order: every key, the action only
    (expert windows with a frozen encoder's features), or none (couplings with features)."""
    sampler = pairs.data.train
    if pairs.features is None:
        return [*sampler.lowdim_keys, *sampler.image_keys, sampler.action_key]
    return [] if isinstance(pairs, CouplingPairs) else [sampler.action_key]


class DeviceBatches:
    """Item `step` is this rank's batch of that step, as the loader's StepBatches makes it
    (the same keys in the same order, dtypes and values), its tensors on `device`."""

    def __init__(self, pairs: ExpertPairs | CouplingPairs, seed: int, batch_size: int,
                 mine: slice, device: torch.device):
        self.pairs, self.seed, self.batch_size, self.mine = pairs, seed, batch_size, mine
        self.device = device
        self.n = len(pairs)
        self.per_epoch = max(1, self.n // batch_size)
        self._epoch, self._order = -1, None
        sampler = pairs.data.train
        self.n_obs_steps, self.action_key = sampler.n_obs_steps, sampler.action_key
        self.coupled = isinstance(pairs, CouplingPairs)
        if self.coupled:
            self.noise, self.target, self.window = (self._up(torch.from_numpy(a)) for a in
                                                    (pairs.noise, pairs.target, pairs.window))
        self.features = None if pairs.features is None else self._up(pairs.features)
        if self.coupled and pairs.features is not None:
            self.feature_row = self._up(torch.from_numpy(pairs.feature_row))
        keys = _keys(pairs)
        self.frames = (self._up(torch.from_numpy(sampler.frame_indices(np.arange(len(sampler)))))
                       if keys else None)
        self.buffers = {k: self._up(torch.from_numpy(np.ascontiguousarray(sampler.buffer(k))))
                        for k in keys}

    def _up(self, t: torch.Tensor) -> torch.Tensor:
        """To the device; on CUDA from pinned memory, so that the host does not wait for it."""
        if self.device.type == "cuda":
            return t.pin_memory().to(self.device, non_blocking=True)
        return t.to(self.device)

    def _indices(self, step: int) -> torch.Tensor:
        """batch_indices(seed, step, n, batch) as a device tensor."""
        epoch, offset = divmod(step, self.per_epoch)
        if epoch != self._epoch:
            order = epoch_order(self.seed, epoch, self.n, self.batch_size)
            self._epoch, self._order = epoch, self._up(torch.from_numpy(order))
        return self._order[offset * self.batch_size:(offset + 1) * self.batch_size]

    def windows(self, w: torch.Tensor) -> dict[str, torch.Tensor]:
        """sampler.batch(w) gathered on the device: observations of the first n_obs_steps
        frames, the action over the whole horizon."""
        frames = self.frames[w]
        obs = frames[:, :self.n_obs_steps]
        return {k: buf[frames if k == self.action_key else obs] for k, buf in self.buffers.items()}

    def __getitem__(self, step: int) -> dict:
        """The loader's fetch (train_batches.ExpertPairs / CouplingPairs), its draws in its
        order: the whole batch's noise (expert windows), then the method's times."""
        idx = self._indices(step)
        gen = step_generator(self.seed, step)
        sel = idx[self.mine]
        cfg = self.pairs.data.cfg
        if not self.coupled:
            x0 = torch.randn(len(idx), cfg.policy.horizon, cfg.shape_meta.action.shape[-1],
                             generator=gen)
            batch = {"x0": self._up(x0[self.mine]), **self._times(len(idx), gen)}
            if self.features is not None:
                batch["cond"] = self.features[sel]
                batch["action"] = self.buffers[self.action_key][self.frames[sel]]
            else:
                batch["obs"] = self.windows(sel)
            return batch
        batch = {"x0": self.noise[sel], "x1": self.target[sel], **self._times(len(idx), gen)}
        if self.features is not None:
            batch["cond"] = self.features[self.feature_row[self.window[sel]]]
        else:
            batch["obs"] = self.windows(self.window[sel])
        return batch

    def _times(self, n: int, gen: torch.Generator) -> dict[str, torch.Tensor]:
        times = _times(self.pairs.method.draw(self.pairs.data.cfg, n, gen), self.mine)
        return {k: self._up(v) for k, v in times.items()}
