"""A sefa policy as LeRobot's `PreTrainedPolicy`: what lerobot-eval, lerobot-rollout and the async
policy server call.

    select_action(batch)         one action (B, Da) per control step, from sefa's executor
                                 (sefa_model/policy/execution.py: the frame history, when to
                                 predict, the noise, which action; receding horizon, ACT's
                                 ensembling or backward coherence, as config.execution says),
                                 one executor per environment of LeRobot's batch
    predict_action_chunk(batch)  the chunk (B, n_action_steps, Da) from the current frame on: a
                                 batch of single frames joins the frame history first (the async
                                 policy server sends one observation a call); (B, To, ...)
                                 histories are used as they are
    reset()                      a new episode: no frames, no plan, the noise seeded again

The batch is LeRobot's, after the preprocessor: `observation.*` tensors (B, *feature shape) on
the policy's device, images float CHW in [0, 1]. Actions are in robot units (the normalizer is
inside the policy: sefa_deploy/lerobot_format.py says why), so the postprocessor only moves
them to the CPU. Training inside LeRobot is not supported: `forward` says so in one line.
"""

from __future__ import annotations

import collections
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from lerobot.policies.pretrained import PreTrainedPolicy

from sefa_deploy.lerobot_format import CONFIG_FILE, WEIGHTS_FILE, ChunkModel, check_files
from sefa_model.policy.execution import ChunkShape, Executor

from .configuration_sefa import TRAIN_WITH_SEFA, SefaConfig


class BatchExecution:
    """sefa's executor for each environment of LeRobot's batch (lerobot-eval steps B of them
    together): frames (B, ...) in, actions (B, Da) out. Each environment's noise is seeded at
    its episode's start: noise_seed + i, or without one a seed drawn from torch's global
    generator (which LeRobot seeds with --seed)."""

    def __init__(self, config: SefaConfig, model: ChunkModel):
        self.settings = config.execution_settings()
        self.shape = ChunkShape(config.n_obs_steps, config.n_action_steps, config.horizon,
                                model.cfg.shape_meta.action.shape[-1])
        self.model, self.noise_seed = model, config.noise_seed
        self.executors: list[Executor] = []

    def reset(self) -> None:
        self.executors = []

    def sample(self, obs: dict[str, np.ndarray], noise: np.ndarray, generator) -> np.ndarray:
        """The executor's sampler: one observation's (1, To, ...) frames per LeRobot name and
        (n, horizon, Da) noise -> its n chunks in robot units (the frames encoded once)."""
        device = next(self.model.parameters()).device
        frames = {k: torch.from_numpy(np.ascontiguousarray(v)).to(device) for k, v in obs.items()}
        chunk = self.model(frames, torch.from_numpy(noise).to(device))
        if not torch.isfinite(chunk).all():
            raise FloatingPointError("the sefa policy produced non-finite actions; none is sent")
        return chunk.float().cpu().numpy()

    def action(self, frames: dict[str, Tensor]) -> np.ndarray:
        batch = next(iter(frames.values())).shape[0]
        if len(self.executors) != batch:  # a new episode (or another batch): new executors
            seeds = ([self.noise_seed + i for i in range(batch)] if self.noise_seed is not None
                     else torch.randint(0, 2 ** 31 - 1, (batch,)).tolist())
            self.executors = [Executor(self.settings, self.sample, self.shape, seed=s)
                              for s in seeds]
        numpy = {k: v.detach().cpu().numpy() for k, v in frames.items()}
        return np.stack([ex.action({k: v[i] for k, v in numpy.items()})
                         for i, ex in enumerate(self.executors)])


class SefaPolicy(PreTrainedPolicy):
    config_class = SefaConfig
    name = "sefa"

    def __init__(self, config: SefaConfig, **kwargs):
        super().__init__(config)
        config.validate_features()
        config.execution_settings()
        self.chunk_model = ChunkModel(config.sefa, config.solver, config.steps, source=CONFIG_FILE)
        self.start = config.n_obs_steps - 1  # the current frame's step in the chunk
        self.features = [m.feature for m in self.chunk_model.inputs]
        self.reset()

    # ---- loading and saving: model.safetensors in sefa's layout, strictly

    @classmethod
    def from_pretrained(cls, pretrained_name_or_path, *args, **kwargs) -> "SefaPolicy":
        """A local folder is checked for every file first (LeRobot would otherwise fail on the
        first one it reads, some only after loading the policy)."""
        if Path(str(pretrained_name_or_path)).is_dir():
            check_files(pretrained_name_or_path)
        return super().from_pretrained(pretrained_name_or_path, *args, **kwargs)

    @classmethod
    def _load_as_safetensor(cls, model: "SefaPolicy", model_file: str, map_location: str,
                            strict: bool) -> "SefaPolicy":
        """Every tensor of the file, none missing or extra, all finite (LeRobot's own loader
        only logs missing keys), or one line naming the file."""
        model.chunk_model.load(Path(model_file))
        return model

    def _save_pretrained(self, save_directory: Path, state_dict=None) -> None:
        from safetensors.torch import save_file

        self.config._save_pretrained(save_directory)
        save_file(self.chunk_model.state_tensors(), str(Path(save_directory) / WEIGHTS_FILE),
                  metadata={"format": "pt"})

    # ---- LeRobot's interface

    def get_optim_params(self) -> dict:
        raise NotImplementedError(TRAIN_WITH_SEFA)

    def forward(self, batch: dict[str, Tensor]) -> tuple[Tensor, dict | None]:
        raise NotImplementedError(TRAIN_WITH_SEFA)

    def reset(self) -> None:
        """A new episode: the frame history and the queued chunks are dropped."""
        self.history: dict[str, collections.deque] = {}  # predict_action_chunk's frames
        self.execution = BatchExecution(self.config, self.chunk_model)
        seed = self.config.noise_seed
        self.generator = None if seed is None else torch.Generator().manual_seed(seed)

    @torch.no_grad()
    def select_action(self, batch: dict[str, Tensor], **kwargs) -> Tensor:
        frames = {f: self._feature(batch, f) for f in self.features}
        action = self.execution.action(frames)
        return torch.from_numpy(action).to(self.device)

    @torch.no_grad()
    def predict_action_chunk(self, batch: dict[str, Tensor], **kwargs) -> Tensor:
        if self._is_history(batch):
            frames = {f: batch[f] for f in self.features}
        else:
            self.observe(batch)
            frames = self.stacked()
        return self.chunk(frames, kwargs.get("noise"))

    # ---- the frame history and the chunk

    @property
    def device(self) -> torch.device:
        return next(self.chunk_model.parameters()).device

    def observe(self, batch: dict[str, Tensor]) -> None:
        """Append this step's frames; the first frame of an episode fills the whole history, as
        Diffusion Policy pads it."""
        to = self.config.n_obs_steps
        for f in self.features:
            frame = self._feature(batch, f).to(self.device)
            queue = self.history.get(f)
            if queue is None or queue[-1].shape != frame.shape:
                queue = self.history[f] = collections.deque([frame] * to, maxlen=to)
            else:
                queue.append(frame)

    def _feature(self, batch: dict[str, Tensor], f: str) -> Tensor:
        if f not in batch:
            raise KeyError(f"the observation has no '{f}' (this sefa policy reads: "
                           f"{', '.join(self.features)}; LeRobot's --rename_map maps names)")
        return batch[f]

    def stacked(self) -> dict[str, Tensor]:
        return {f: torch.stack(list(q), dim=1) for f, q in self.history.items()}

    def _is_history(self, batch: dict[str, Tensor]) -> bool:
        """(B, To, *shape) rather than (B, *shape), told by the feature's declared shape."""
        f = self.features[0]
        if f not in batch:
            return False
        return batch[f].ndim == len(self.config.input_features[f].shape) + 2

    def chunk(self, frames: dict[str, Tensor], noise: Tensor | None = None) -> Tensor:
        """(B, n_action_steps, Da) in robot units: the steps of the predicted chunk from the
        current frame on. The noise, unless given, is drawn on the CPU from the policy's
        generator (config.noise_seed) or torch's global one (which LeRobot seeds)."""
        batch = next(iter(frames.values())).shape[0]
        x0 = noise if noise is not None else self.chunk_model.noise(batch, self.device, self.generator)
        full = self.chunk_model(frames, x0.to(self.device))
        if not torch.isfinite(full).all():
            raise FloatingPointError("the sefa policy produced non-finite actions; none is sent")
        return full[:, self.start:self.start + self.config.n_action_steps]

