"""A store as a policy sees it: the train and validation windows, the normalizer fitted on the
training split, and the processor that turns raw windows into model inputs.

    data = PolicyData(cfg, EpisodeStore.open(path), normalizer)   # normalizer None: fit it
    obs, chunk = data.tensors(data.train, windows, device)        # model inputs, (B, T, Da)
"""

from __future__ import annotations

import numpy as np
import torch

from sefa_data.normalizer import Normalizer, train_frames
from sefa_data.sampler import SequenceSampler, to_torch
from sefa_data.store.zarr_store import EpisodeStore
from sefa_model.config import TrainConfig
from sefa_model.policy.processor import Processor, lowdim_view


class PolicyData:
    """Samplers for both splits and the normalizer, turning windows into model inputs."""

    def __init__(self, cfg: TrainConfig, store: EpisodeStore, normalizer: Normalizer | None):
        p, meta = cfg.policy, cfg.shape_meta
        keys = list(meta.obs)
        self.cfg = cfg
        self.image_keys = [k for k, s in meta.obs.items() if s.type == "rgb"]
        kwargs = dict(horizon=p.horizon, n_obs_steps=p.n_obs_steps, n_action_steps=p.n_action_steps,
                      obs_keys=keys, action_key=meta.action.key)
        self.train = SequenceSampler(store, split="train", **kwargs)
        self.valid = SequenceSampler(store, split="valid", **kwargs) if store.mask("valid").any() else None
        self.split_note = None
        if self.valid is None and len(self.train) > p.horizon:
            from sefa_data.sampler import WindowSubset, window_split

            # one episode: no episode to hold out, so hold out the episode's last windows
            tr, va = window_split(len(self.train), p.horizon)
            self.split_note = (f"{len(store.episode_ends)} episode(s), none in the validation split: "
                               f"a window-level split instead ({len(tr)} training windows, the last "
                               f"{len(va)} for validation, {len(self.train) - len(tr) - len(va)} "
                               f"between them dropped so that none shares a frame)")
            self.train, self.valid = WindowSubset(self.train, tr, "train"), WindowSubset(self.train, va, "valid")
        self.store = store
        self.normalizer: Normalizer | None = None
        self.processor: Processor | None = None
        if normalizer is not None:
            self.use_normalizer(normalizer)
        # the validation baseline: always predict the training set's mean action
        self.mean_action = train_frames(store, meta.action.key).astype(np.float64).mean(0)

    def use_normalizer(self, normalizer: Normalizer) -> None:
        self.normalizer = normalizer
        self.processor = Processor(self.cfg.shape_meta, normalizer)

    def fit_normalizer(self) -> Normalizer:
        """Fitted on the training split only, on exactly the values the model will see."""
        meta = self.cfg.shape_meta
        data = {meta.action.key: train_frames(self.store, meta.action.key)}
        modes = {meta.action.key: self.cfg.normalizer.action}
        for key, spec in meta.obs.items():
            if spec.type == "low_dim":
                data[key] = lowdim_view(key, spec, train_frames(self.store, key)[:, None])[:, 0]
                modes[key] = self.cfg.normalizer.obs
        return Normalizer.fit(data, modes, range_eps=self.cfg.normalizer.range_eps)

    def provenance(self) -> dict:
        """What couplings made on these windows record (sefa_model.data.couplings.provenance)."""
        from sefa_model.data.couplings import provenance

        return provenance(self.normalizer.digest(), self.cfg, len(self.train))

    def tensors(self, sampler: SequenceSampler, idx: np.ndarray, device: torch.device
                ) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
        """(model inputs, normalized action chunk (B, T, Da)) for windows `idx`."""
        raw = to_torch(sampler.batch(idx), device, self.image_keys)
        return self.obs_tensors(raw), self.normalize_actions(raw[self.cfg.shape_meta.action.key])

    def expert_chunks(self, windows: np.ndarray) -> np.ndarray:
        """(len(windows), T, Da) float32: the normalized expert chunks of training windows."""
        chunks = self.processor.action.normalize(self.train.actions(windows))
        return np.asarray(chunks).astype(np.float32)

    def normalize_actions(self, chunks: torch.Tensor) -> torch.Tensor:
        return self._on(chunks).action.normalize(chunks)

    def obs_tensors(self, raw: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """Raw windows (images already float CHW, or uint8 HWC) -> the network's inputs."""
        some = next(iter(raw.values()))
        return self._on(some).obs(raw)

    def host_batch(self, sampler: SequenceSampler, idx: np.ndarray) -> dict[str, torch.Tensor]:
        """The raw windows as CPU tensors (images still uint8 HWC): what a loader worker makes."""
        return {k: torch.from_numpy(np.ascontiguousarray(v)) for k, v in sampler.batch(idx).items()}

    def device_obs(self, raw: dict[str, torch.Tensor], device: torch.device) -> dict[str, torch.Tensor]:
        """Host windows -> normalized model inputs on `device`. Copies are non-blocking (from
        pinned memory they overlap the running step) and images cross as uint8, a quarter of
        the bytes, to be converted on the device."""
        moved = {k: raw[k].to(device, non_blocking=True) for k in self.cfg.shape_meta.obs}
        return self.obs_tensors({k: v if k in self.image_keys else v.float() for k, v in moved.items()})

    def _on(self, like: torch.Tensor) -> Processor:
        """The processor on `like`'s device (its buffers follow the data, moved once)."""
        if isinstance(like, torch.Tensor) and self.processor.action.norm.scale.device != like.device:
            self.processor.to(like.device)
        return self.processor
