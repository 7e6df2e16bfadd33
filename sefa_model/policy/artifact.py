"""A trained policy, loaded from a checkpoint directory, that turns observations into actions.

    policy = Policy.load("train/checkpoints/latest")
    out = policy.predict_action({"keypoint": kp, "state": st})   # (To, ...) or (B, To, ...)
    out.action          # (B, n_action_steps, Da): what to execute now
    out.action_pred     # (B, horizon, Da): the whole predicted chunk
    out.nfe             # network evaluations used

The same class serves the diffusion baseline (`kind == "ddpm"`), sampled with ddpm or ddim.

Observation values are the store's raw values (the normalizer is part of the checkpoint);
images are uint8 HWC or float CHW in [0, 1].
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from sefa_data.errors import SefaInputError
from sefa_data.normalizer import Normalizer
from sefa_model.policy.checkpoint import load_weights, open_policy, read_json
from sefa_model.config import TrainConfig, saved_train_config
from sefa_model.flow.cuda_graphs import CapturedCall, GraphCache
from sefa_model.distributed import cpu_noise, resolve_device
from sefa_model.policy.model import FlowPolicyModel
from sefa_model.policy.processor import PROCESSOR_FILE, Processor

# network evaluations per step of the fixed-step flow solvers (what a compiled graph unrolls)
FIXED_STEP = {"euler": 1, "midpoint": 2, "rk4": 4}


@dataclass
class Prediction:
    action: torch.Tensor  # (B, n_action_steps, Da), action units
    action_pred: torch.Tensor  # (B, horizon, Da)
    nfe: int


class Policy:
    def __init__(self, cfg: TrainConfig, model: FlowPolicyModel, normalizer: Normalizer,
                 kind: str = "base_flow", path: str = ""):
        self.cfg, self.model, self.normalizer, self.kind, self.path = cfg, model.eval(), normalizer, kind, path
        self.device = next(model.parameters()).device
        self.processor = Processor(cfg.shape_meta, normalizer).to(self.device)
        self.weights: str | None = None  # the file of the checkpoint loaded (set by load)
        self._compiled = None
        # on CUDA a batch-1 call of a fixed-step sampler replays a CUDA graph of the encoder and
        # the sampler (see `captured`); False: always eager. The CPU stays eager.
        self.capture = self.device.type == "cuda"
        self._graphs = GraphCache()  # None: capture failed, eager

    def compile(self, mode: str | None = None) -> "Policy":
        """Compile the encoder and a fixed-step sampler (one-step policies, Euler-N) into one
        graph with torch.compile; on a GPU `reduce-overhead` replays it as a CUDA graph, so that
        the small ops around the network stop costing a kernel launch each. Adaptive solvers
        (rk45, which decides its steps on the host) and the diffusion samplers stay eager.
        The first call of each setting compiles (seconds to minutes)."""
        mode = mode or ("reduce-overhead" if self.device.type == "cuda" else "default")
        self._compiled = torch.compile(self._encode_and_sample, mode=mode, dynamic=False)
        return self

    def _encode_and_sample(self, o: dict[str, torch.Tensor], x0: torch.Tensor, solver: str,
                           steps: int | None) -> torch.Tensor:
        return self.model.sample(self.model.encode(o, samples=x0.shape[0]), x0, solver=solver,
                                 steps=steps).x

    @classmethod
    def load(cls, path: str | Path, *, device: str | torch.device = "auto", ema: bool = True) -> "Policy":
        """`device`: auto (CUDA, then MPS, then the CPU), cpu, cuda, cuda:N or mps. `ema`: the
        EMA weights (what evaluation and deployment use); False for the raw weights.

        The checkpoint is checked first (sefa_model/policy/checkpoint.py: checksums, config.json,
        finite weights), so a damaged one is a clear error, never a policy that outputs NaN."""
        device = resolve_device(device)
        ckpt, meta, weights = open_policy(path, ema)
        cfg = saved_train_config(meta["train_config"], source=str(ckpt / "config.json"))
        if cfg.shape_meta.action.shape is None:
            raise SefaInputError("config.json lacks resolved shapes", file=str(ckpt / "config.json"))
        model = FlowPolicyModel(cfg)
        load_weights(model, weights)
        policy = cls(cfg, model.to(device), Normalizer.load(ckpt), meta.get("kind", "base_flow"), str(ckpt))
        _check_processor(ckpt, policy.processor)
        policy.weights = weights.name
        return policy

    @property
    def n_action_steps(self) -> int:
        return self.cfg.policy.n_action_steps

    def prepare_obs(self, obs: dict) -> dict[str, torch.Tensor]:
        """Raw observations -> the model's inputs: (B, To, ...) float tensors on the device,
        low-dim keys normalized, images CHW in [0, 1]."""
        meta, to = self.cfg.shape_meta, self.cfg.policy.n_obs_steps
        out = {}
        for key, spec in meta.obs.items():
            if key not in obs:
                raise SefaInputError(f"observation '{key}' missing (the policy needs: "
                                     f"{', '.join(meta.obs)})", key=key)
            x = obs[key]
            if not torch.is_tensor(x):
                # low-dim arrays stay in numpy until normalized: the same float32 arithmetic,
                # at a fraction of torch's per-op cost on arrays this small
                x = np.asarray(x, dtype=np.float32) if spec.type == "low_dim" else torch.as_tensor(np.asarray(x))
            if x.ndim == len(spec.frame_shape) + 1:  # one observation history, no batch axis
                x = x[None]
            if x.ndim != len(spec.frame_shape) + 2:
                raise SefaInputError(f"observation '{key}' has shape {tuple(x.shape)}; expected "
                                     f"(B, {to}, {', '.join(map(str, spec.frame_shape))}) or without B",
                                     key=key)
            if x.shape[1] != to:
                raise SefaInputError(f"observation '{key}' has {x.shape[1]} frames, the policy "
                                     f"needs n_obs_steps = {to}", key=key)
            if torch.is_tensor(x):
                x = x.to(self.device) if x.dtype == torch.uint8 else x.to(self.device, torch.float32)
            out[key] = self.processor.obs.one(key, x).to(self.device)
        return out

    @torch.inference_mode()  # cheaper than no_grad per op; the outputs are never trained on
    def predict_action(self, obs: dict, *, solver: str | None = None, steps: int | None = None,
                       generator: torch.Generator | None = None, noise: torch.Tensor | None = None
                       ) -> Prediction:
        """Sample an action chunk from noise (an ODE solve for a flow, the reverse process for the
        diffusion baseline); solver and steps default to the checkpoint's.

        The noise is `noise` if given, else drawn by `generator` on its own device: a CPU
        generator (the default) gives the same noise, so the same chunk up to float error, on
        every device; a CUDA generator draws on the GPU without a copy. One observation with
        `noise` of batch N gives its N chunks, the observation encoded once."""
        p = self.cfg.policy
        o = self.prepare_obs(obs)
        batch = next(iter(o.values())).shape[0]  # `noise` of batch N may follow 1 observation
        shape = (batch, p.horizon, self.cfg.shape_meta.action.shape[-1])
        x0 = noise.to(self.device) if noise is not None else cpu_noise(shape, generator, self.device)
        solver, steps = self.model.method.resolve_solver(self.cfg, solver, steps)
        graph = self.captured(o, x0, solver, steps) if self._compiled is None else None
        if self._compiled is not None and solver in FIXED_STEP:
            # a CUDA graph's output is overwritten by its next replay: keep a copy
            x, nfe = self._compiled(o, x0, solver, steps).clone(), steps * FIXED_STEP[solver]
        elif graph is not None:
            x, nfe = graph(o, x0), steps * FIXED_STEP[solver]
        else:
            result = self.model.sample(self.model.encode(o, samples=x0.shape[0]), x0,
                                       solver=solver, steps=steps, generator=generator)
            x, nfe = result.x, result.nfe
        chunk = self.processor.action.unnormalize(x)
        start = p.n_obs_steps - 1  # DP: act from the current (last observed) frame on
        return Prediction(chunk[:, start:start + p.n_action_steps], chunk, nfe)

    def captured(self, o: dict[str, torch.Tensor], x0: torch.Tensor, solver: str,
                 steps: int | None) -> CapturedCall | None:
        """The CUDA graph of this call's encoder and sampler, recorded on its first call, or
        None where a call runs eager: off CUDA, `capture` off, a batch other than 1 (the one
        shape a controller sends; other batches would each record a graph), an adaptive or
        diffusion sampler (their steps are decided on the host), or a capture that failed."""
        if not (self.capture and solver in FIXED_STEP and x0.shape[0] == 1):
            return None
        key = (solver, steps, x0.shape, *((k, v.shape, v.dtype) for k, v in o.items()))
        return self._graphs.recorded(
            key, lambda oo, xx: self._encode_and_sample(oo, xx, solver, steps), o, x0,
            failing=lambda: f"{self.path}: running eager, the CUDA graph capture of {solver}-{steps} failed")


def _check_processor(ckpt: Path, processor: Processor) -> None:
    """processor.json (checkpoints since it was written) must describe what the config and the
    normalizer build: an edited config.json or a normalizer from elsewhere is refused."""
    path = ckpt / PROCESSOR_FILE
    if path.exists() and read_json(path) != processor.describe():
        raise SefaInputError("processor.json does not match config.json and the normalizer "
                             "(was one of them edited or copied from another run?)", file=str(path))
