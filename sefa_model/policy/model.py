"""The velocity network of a flow policy: observation encoder + action head.

Shapes: observations arrive as a dict of (B, To, ...) tensors, already normalized (low-dim) or in
[0, 1] (images, (B, To, C, H, W)); the action chunk is (B, T, Da) in normalized space.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from sefa_data.errors import ConfigError
from sefa_data.store.zarr_store import EpisodeStore
from sefa_model.config import ObsSpec, TrainConfig, model_image_size
from sefa_model.flow.cuda_graphs import FieldGraphs
from sefa_model.nets.encoders import ObsEncoder
from sefa_model.methods import method_of
from sefa_model.nets.networks import build_head
from sefa_model.flow.solvers import SolveResult


# The step size reaches its (new, zero-initialised) embedding unscaled: sin(d f) with f <= 1 is
# smooth in d. At the time's scale (999) the embedding's derivative in d grows with every update,
# and the mean-flow target, which differentiates the network along d, diverged (its one-step
# chunks reached 1e4 normalized units within 1,000 steps on Push-T).
STEP_SCALE = 1.0

# robomimic files carry these per step; they are outcomes, not observations
NOT_OBSERVATIONS = {"reward", "done"}


def store_observation_keys(cfg: TrainConfig, features: dict) -> list[str]:
    """The store's observation keys, by name: every key but the action and the outcomes."""
    action_key = cfg.shape_meta.action.key
    return sorted(k for k in features if k != action_key and k not in NOT_OBSERVATIONS)


def observation_keys(cfg: TrainConfig, store: EpisodeStore) -> tuple[list[str], list[str]]:
    """(the observation keys the policy reads, in order; the store's observation keys it leaves
    out). The set is `shape_meta.obs_keys` when given, else every store observation key by name
    plus any other key `shape_meta.obs` names; `shape_meta.obs` alone never removes a key."""
    meta = cfg.shape_meta
    available = store_observation_keys(cfg, store.attrs["features"])
    used = (list(meta.obs_keys) if meta.obs_keys is not None
            else available + [k for k in meta.obs if k not in available])
    return used, [k for k in available if k not in used]


def resolve_shapes(cfg: TrainConfig, store: EpisodeStore) -> TrainConfig:
    """Fill `shape_meta` from the store: the observation set (`observation_keys`), each key's
    spec (as `shape_meta.obs` sets it, else its type from the store) and shapes, the action
    shape. Afterwards `obs_keys` and `obs` list the same keys in the same order."""
    features = store.attrs["features"]
    meta = cfg.shape_meta
    action_key = meta.action.key
    if action_key not in features:
        raise ConfigError(f"action key '{action_key}' is not in the store (keys: "
                          f"{', '.join(sorted(features))})", file=str(store.path),
                          key="shape_meta.action.key")
    shape = list(features[action_key]["shape"])
    if len(shape) > 1 and any(d != 1 for d in shape[:-1]):
        raise ConfigError(f"the action '{action_key}' holds {tuple(shape)} values per frame; a "
                          f"policy predicts one vector per frame (leading axes of size 1 are "
                          f"dropped, as LeRobot reads them)", file=str(store.path),
                          key="shape_meta.action.key")
    meta.action.shape = shape[-1:]  # (1, Da) per frame is read as Da values: sefa_data's sampler
    used, _ = observation_keys(cfg, store)
    if not used:
        raise ConfigError("the policy would see no observation key", key="shape_meta.obs_keys")
    if len(set(used)) != len(used):
        raise ConfigError(f"a key is named twice: {used}", key="shape_meta.obs_keys")
    stray = [k for k in meta.obs if k not in used]
    if stray:
        raise ConfigError(f"'{stray[0]}' is configured in shape_meta.obs but not in "
                          f"shape_meta.obs_keys ({', '.join(used)}): add it there, or drop its "
                          f"settings", key=f"shape_meta.obs.{stray[0]}")
    for key in used:
        if key not in features:
            where = "obs_keys" if meta.obs_keys is not None else f"obs.{key}"
            raise ConfigError(f"observation key '{key}' is not in the store (keys: "
                              f"{', '.join(sorted(features))})", file=str(store.path),
                              key=f"shape_meta.{where}")
    meta.obs = {k: meta.obs.get(k) or ObsSpec(type="rgb" if features[k]["type"] == "image"
                                               else "low_dim") for k in used}
    meta.obs_keys = list(used)
    for key, spec in meta.obs.items():
        shape = list(features[key]["shape"])
        spec.frame_shape = list(shape)
        if spec.type == "rgb":
            if features[key]["type"] != "image":
                raise ConfigError(f"'{key}' is {features[key]['type']} in the store, not an image",
                                  key=f"shape_meta.obs.{key}.type")
            size = model_image_size((shape[0], shape[1]), spec.resize, cfg.policy.resize_shape)
            spec.resize = list(size) if size else None  # resolved: the checkpoint says it
            h, w = size or (shape[0], shape[1])
            spec.shape = [shape[2], h, w]  # stored HWC, fed CHW at the model size
            _check_crop(cfg.policy.crop_shape, key, h, w)
        else:
            if spec.resize is not None:  # it was once accepted and ignored
                hint = (f" (the store holds images there: shape_meta.obs.{key}.type=rgb)"
                        if features[key]["type"] == "image" else "")
                raise ConfigError(f"resize sets a camera's model size, and '{key}' is read as "
                                  f"low_dim{hint}", key=f"shape_meta.obs.{key}.resize")
            if spec.dims is not None:
                if spec.dims[1] > shape[-1]:
                    raise ConfigError(f"dims {spec.dims} exceed the last axis ({shape[-1]}) of '{key}'",
                                      key=f"shape_meta.obs.{key}.dims")
                shape = shape[:-1] + [spec.dims[1] - spec.dims[0]]
            spec.shape = [int(np.prod(shape))]
    return cfg


def _check_crop(crop: list[int] | None, key: str, h: int, w: int) -> None:
    """policy.crop_shape must fit every camera at its model size (the encoder's crop)."""
    if crop is not None and (crop[0] > h or crop[1] > w):
        raise ConfigError(f"{list(crop)} does not fit camera '{key}', whose frames the model sees "
                          f"at {h}x{w} (shape_meta.obs.{key}.resize or policy.resize_shape set "
                          "that size): crop at most that", key="policy.crop_shape")


def observation_record(cfg: TrainConfig) -> dict[str, dict]:
    """A resolved config's observations as a run records them, in the network's order:
    {key: {type, frame_shape as stored, dims, shape the network sees}}."""
    return {k: {"type": s.type, "frame_shape": s.frame_shape, "dims": s.dims, "shape": s.shape,
                **({"resize": s.resize} if s.resize else {})}
            for k, s in cfg.shape_meta.obs.items()}


def describe_observation(key: str, rec: dict) -> str:
    """`state (5,)[0:2]`: the key, one frame's shape as stored, the slice read from it."""
    text = f"{key} {tuple(rec['frame_shape'])}"
    text += f"[{rec['dims'][0]}:{rec['dims'][1]}]" if rec.get("dims") else ""
    text += " rgb" if rec["type"] == "rgb" else ""
    if rec.get("resize"):
        text += (f" resized to {rec['resize'][0]}x{rec['resize'][1]} (shape_meta.obs.KEY.resize "
                 "or policy.resize_shape set the model size)")
    return text


class FlowPolicyModel(nn.Module):
    """v_theta(x_t, t, obs): `encode` the observation once, then call `velocity` per ODE step.

    How the network is read and sampled is its method's (`self.method`, sefa_model/methods): a
    flow's velocity integrated by an ODE solver, or, for the diffusion baseline, the same network
    read as a noise predictor (`predict_noise(x_k, k, cond)`, the integer timestep k fed as
    Diffusion Policy feeds it) and run backwards by its scheduler.
    """

    def __init__(self, cfg: TrainConfig):
        super().__init__()
        p, meta = cfg.policy, cfg.shape_meta
        self.cfg = cfg  # the sampling convention (flow time, solver, diffusion schedule)
        self.time_scale = cfg.flow.time_scale
        shape_meta = {"obs": {k: {"shape": s.shape, "type": s.type} for k, s in meta.obs.items()}}
        self.obs_encoder = ObsEncoder(shape_meta, p.n_obs_steps,
                                      image_feature_dim=p.image_feature_dim,
                                      crop_shape=tuple(p.crop_shape) if p.crop_shape else None,
                                      image_encoder=p.image_encoder, image_pool=p.image_pool)
        action_dim = meta.action.shape[-1]
        self.method = method_of(cfg)
        # a student that takes the step size (shortcut, mean flow) has one more embedding
        step = {"step_input": True} if self.method.step_input else {}
        if p.head == "unet":
            self.head = build_head("unet", input_dim=action_dim,
                                   global_cond_dim=self.obs_encoder.out_dim,
                                   time_embed_dim=p.time_embed_dim, down_dims=tuple(p.down_dims),
                                   kernel_size=p.kernel_size, n_groups=p.n_groups, **step)
        else:
            self.head = build_head("mlp", input_dim=action_dim, horizon=p.horizon,
                                   global_cond_dim=self.obs_encoder.out_dim,
                                   time_embed_dim=p.time_embed_dim,
                                   hidden_dims=tuple(p.mlp_hidden_dims), **step)

    def forward(self, obs: dict[str, torch.Tensor] | torch.Tensor, x: torch.Tensor, t: torch.Tensor,
                d: torch.Tensor | None = None) -> torch.Tensor:
        """One training evaluation; DDP needs the gradient-carrying call to go through forward.
        `obs` is the observation dict, or the already encoded condition (B, D) of a frozen
        encoder. t is the flow time in [0, 1], or the diffusion baseline's integer timestep; d the
        step size (B,) of a student with a step input."""
        cond = obs if torch.is_tensor(obs) else self.encode(obs)
        return self.method.network(self, x, t, cond, d)

    def encode(self, obs: dict[str, torch.Tensor], samples: int | None = None) -> torch.Tensor:
        """(B, To, ...) per key -> (B, D) global condition. With `samples` n and B = 1: the one
        observation's condition (n, D) for n noises, encoded once (an execution choosing among
        n samples runs the image encoder once, not n times)."""
        cond = self.obs_encoder(obs)
        if samples is None or samples == cond.shape[0]:
            return cond
        if cond.shape[0] != 1:
            raise ValueError(f"{cond.shape[0]} observations for {samples} noises: give one "
                             "observation, or one per noise")
        return cond.expand(samples, *cond.shape[1:]).contiguous()  # heads may reshape it

    def velocity(self, x: torch.Tensor, t: torch.Tensor, cond: torch.Tensor,
                 d: torch.Tensor | float | None = None) -> torch.Tensor:
        """x: (B, T, Da), t: (B,) in [0, 1], cond: (B, D), d: the step size (B,) of a student
        with a step input (None: 0, the instantaneous velocity) -> (B, T, Da)."""
        if d is None:
            return self.head(x, t * self.time_scale, cond)
        return self.head(x, t * self.time_scale, cond, step=torch.as_tensor(d) * STEP_SCALE)

    def predict_noise(self, x: torch.Tensor, k: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        """x: (B, T, Da) noised chunk, k: (B,) timesteps in [0, num_train_timesteps) -> (B, T, Da)."""
        return self.head(x, k, cond)

    def sample(self, cond: torch.Tensor, noise: torch.Tensor, *, solver: str | None = None,
               steps: int | None = None, generator: torch.Generator | None = None,
               rtol: float | None = None, atol: float | None = None,
               graphs: FieldGraphs | None = None) -> SolveResult:
        """cond (B, D), noise (B, T, Da) -> the normalized chunk (B, T, Da) and its NFE: the one
        sampler (policy, validation, evaluation, reflow's couplings, the export), as the
        policy's method samples (`Method.sample`): a flow integrates its velocity over
        `FlowConfig.time_span`, the diffusion baseline runs its reverse process. Solver and steps
        default to the checkpoint's; rtol/atol (adaptive solvers) too, so that reflow can solve
        at its own tolerance. `graphs` (on CUDA): a flow's velocity replays a CUDA graph at
        every evaluation of a whole-batch solver (reflow's batched solves)."""
        solver, steps = self.method.resolve_solver(self.cfg, solver, steps)
        return self.method.sample(self, cond, noise, solver, steps, generator=generator,
                                  rtol=rtol, atol=atol, graphs=graphs)
