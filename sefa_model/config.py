"""Training configuration: typed dataclasses with Diffusion Policy's names and defaults.

A YAML file gives any subset; `key=value` overrides on the command line come after it; unknown
keys are errors that name the nearest valid key. The fully resolved config (shapes included) is
written into every checkpoint as `config.json`.

    dataset: dataset.zarr
    shape_meta:
      obs_keys: [keypoint, state]               # the observation set, in this order (default:
                                                # every store key but the action, by name)
      obs:
        state: {type: low_dim, dims: [0, 2]}    # the agent position only; keypoint as stored
      action: {key: action}
    policy: {horizon: 16, n_obs_steps: 2, n_action_steps: 8, head: unet}
    training: {batch_size: 256, max_steps: 5000}
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from sefa_data.config_io import apply_overrides, from_dict, load_yaml, to_dict
from sefa_data.errors import ConfigError
from sefa_data.ranges import (NONNEGATIVE, POSITIVE, SEED, UNIT, UNIT_OPEN, Range, count,
                               knob)


@dataclass
class ObsSpec:
    type: Literal["low_dim", "rgb"] = "low_dim"
    shape: list[int] | None = knob(None, count(1))  # what the model sees (CHW, or a flat vector); from the store
    frame_shape: list[int] | None = knob(None, count(1))  # one frame as stored (HWC, or e.g. (9, 2)); from the store
    dims: list[int] | None = knob(None, count(0))  # [start, stop) slice of the last axis, e.g. state[:, 0:2]
    # rgb: [h, w] the camera's frames are resized to before the encoder (the model size, as
    # LeRobot's resize_shape), in the processor, so training, predict_action, the export and the
    # server resize alike; None: policy.resize_shape, else the automatic size (see PolicyConfig)
    resize: list[int] | None = knob(None, count(1, 65_536))

    def validate(self) -> None:
        if self.dims is not None and (len(self.dims) != 2 or self.dims[0] >= self.dims[1]):
            raise ConfigError("dims must be [start, stop) with start < stop", key="dims")
        if self.resize is not None and len(self.resize) != 2:
            raise ConfigError(f"resize must be [height, width], got {self.resize}", key="resize")


@dataclass
class ActionSpec:
    key: str = "action"
    shape: list[int] | None = knob(None, count(1))  # filled from the store


@dataclass
class ShapeMeta:
    """`obs_keys` is the observation set and its order (the network's input layout and the
    deployed inputs' order); None: every store key but the action and reward/done, sorted by
    name. `obs` sets how a key is read (type, dims) and changes that key only: naming one key
    there never drops the others (it once did: a Push-T command naming `state` there trained
    on `state` alone). Once resolved against the store, both list the same keys."""

    obs_keys: list[str] | None = None
    obs: dict[str, ObsSpec] = field(default_factory=dict)
    action: ActionSpec = field(default_factory=ActionSpec)


@dataclass
class PolicyConfig:
    horizon: int = knob(16, count(1, 10_000))
    n_obs_steps: int = knob(2, count(1, 10_000))
    n_action_steps: int = knob(8, count(1, 10_000))
    head: Literal["unet", "mlp"] = "unet"
    down_dims: list[int] = knob(valid=count(1, 65_536), factory=lambda: [256, 512, 1024])
    time_embed_dim: int = knob(256, count(1, 65_536))
    kernel_size: int = knob(5, count(1, 99))
    n_groups: int = knob(8, count(1, 65_536))
    mlp_hidden_dims: list[int] = knob(valid=count(1, 65_536), factory=lambda: [512, 512, 512])
    # Images (rgb keys), one encoder per camera. "small": our small ResNet ("tiny": half its
    # widths, one block per stage, about 1/8 of its compute, for 2 CPU cores);
    # "resnet18": torchvision's ResNet-18 with GroupNorm (Diffusion Policy, robomimic). Pooled by
    # spatial-softmax keypoints (robomimic; DP's CNN image policy) or a global average (DP's
    # MultiImageObsEncoder), then a Linear to image_feature_dim; null keeps the pooled features
    # (32 keypoints: 64; avg: the trunk's width, 256 small, 512 resnet18).
    image_encoder: Literal["tiny", "small", "resnet18"] = "small"
    image_pool: Literal["spatial_softmax", "avg"] = "spatial_softmax"
    image_feature_dim: int | None = knob(64, count(1, 65_536))
    crop_shape: list[int] | None = knob(None, count(1, 65_536))  # [h, w]: random crop in training, center crop at eval
    # [h, w] every camera is resized to (a key's shape_meta.obs.KEY.resize overrides it); None:
    # frames with a side over AUTO_RESIZE_ABOVE pixels are resized so that their short side is
    # AUTO_RESIZE_SIDE (aspect kept, announced), smaller ones are kept: a 480x640 camera would
    # cost tens of seconds per CPU step at its recorded size (Diffusion Policy and LeRobot
    # train at 96x96 or 84x84)
    resize_shape: list[int] | None = knob(None, count(1, 65_536))

    def validate(self) -> None:
        if self.n_obs_steps < 1 or self.n_action_steps < 1:
            raise ConfigError("n_obs_steps and n_action_steps must be at least 1", key="n_obs_steps")
        if self.n_obs_steps - 1 + self.n_action_steps > self.horizon:
            raise ConfigError(f"n_obs_steps - 1 + n_action_steps ({self.n_obs_steps - 1 + self.n_action_steps}) "
                              f"exceeds horizon ({self.horizon})", key="n_action_steps")
        if self.image_feature_dim is not None and self.image_feature_dim < 1:
            raise ConfigError(f"image_feature_dim must be a positive width or null (no projection), "
                              f"got {self.image_feature_dim}", key="image_feature_dim")
        if self.resize_shape is not None and len(self.resize_shape) != 2:
            raise ConfigError(f"resize_shape must be [height, width], got {self.resize_shape}",
                              key="resize_shape")
        if self.crop_shape is not None and (len(self.crop_shape) != 2 or min(self.crop_shape) < 1):
            raise ConfigError(f"crop_shape must be [height, width], positive, got {self.crop_shape}",
                              key="crop_shape")


AUTO_RESIZE_ABOVE = 128  # a camera side above this is resized by default
AUTO_RESIZE_SIDE = 96  # ... to this short side (Diffusion Policy's Push-T and robomimic size)


def model_image_size(frame_hw: tuple[int, int], resize: list[int] | None,
                     default: list[int] | None) -> tuple[int, int] | None:
    """The [h, w] a camera's frames are resized to, None for none: the key's own `resize`, else
    policy.resize_shape, else the automatic size for frames larger than AUTO_RESIZE_ABOVE."""
    chosen = resize or default
    if chosen is not None:
        size = (int(chosen[0]), int(chosen[1]))
        return None if size == tuple(frame_hw) else size
    h, w = frame_hw
    if max(h, w) <= AUTO_RESIZE_ABOVE:
        return None
    short = min(h, w)
    return (round(h * AUTO_RESIZE_SIDE / short), round(w * AUTO_RESIZE_SIDE / short))


# the ODE solvers by name (sefa_model/flow/solvers.py implements them; tests check the two agree),
# here so that reading a config never imports torch
SOLVERS = ("euler", "midpoint", "rk4", "rk45", "rk45-ps", "dop853-ps")


@dataclass
class FlowConfig:
    """The rectified-flow convention; stored in every checkpoint.

    Noise x0 ~ N(0, I) at t = 0, data x1 (the normalized action chunk) at t = 1,
    x_t = t * x1 + (1 - t) * x0, the network predicts the velocity x1 - x0, and the network sees
    t * time_scale (SeFA's reference code: 999). Sampling integrates from t = t_eps to 1.

    `t_train` is where the velocity is trained: "uniform", t ~ U[t_eps, 1] (a flow, base or
    reflowed); "start", t = t_eps only (the one-step student: x0 + (1 - t_eps) v(x0, t_eps)
    lands on the target); or "grid", the `steps` times an Euler sampler of `steps` steps visits,
    t_eps + i (1 - t_eps) / steps (a k-step student: on a straight coupling the velocity is
    x1 - x0 at every one of them, so k exact Euler steps land on the target; "start" is the
    grid of one). Sampling reads both from the checkpoint, so a student is always evaluated at
    the times it was trained at.
    """

    t_eps: float = knob(1e-3, UNIT_OPEN)
    t_train: Literal["uniform", "start", "grid"] = "uniform"
    time_scale: float = knob(999.0, POSITIVE)
    solver: Literal["euler", "midpoint", "rk4", "rk45", "rk45-ps", "dop853-ps"] = "rk45"
    steps: int | None = knob(None, count(1, 100_000))  # fixed-step solvers
    rtol: float = knob(1e-5, POSITIVE)
    atol: float = knob(1e-5, POSITIVE)

    @property
    def time_span(self) -> tuple[float, float]:
        """(start, end) of sampling: from the noise end, kept t_eps away from it, to the data."""
        return float(self.t_eps), 1.0

    def convention(self) -> dict:
        """The convention in words, written into every checkpoint's config.json."""
        t0, t1 = self.time_span
        t_train = {"uniform": f"U[{self.t_eps:g}, 1]", "start": f"{self.t_eps:g} (one step)",
                   "grid": f"the {self.steps} Euler times from {self.t_eps:g} ({self.steps} steps)"}[self.t_train]
        return {"noise_at": 0.0, "data_at": 1.0, "x_t": "t * x1 + (1 - t) * x0", "target": "x1 - x0",
                "t_train": t_train, "t_sample": f"from {t0:g} to {t1:g}",
                "network_time": f"t * {self.time_scale:g}"}

    def validate(self) -> None:
        if not 0.0 <= self.t_eps < 1.0:
            raise ConfigError(f"t_eps must be in [0, 1), got {self.t_eps}", key="t_eps")
        if self.t_train == "start" and (self.solver, self.steps) != ("euler", 1):
            raise ConfigError(f"a policy trained at t = t_eps only (t_train: start) samples with one "
                              f"Euler step; got solver {self.solver} steps {self.steps}",
                              key="solver")
        if self.t_train == "grid" and (self.solver != "euler" or not self.steps):
            raise ConfigError(f"a policy trained on the Euler grid (t_train: grid) samples with the "
                              f"Euler steps of that grid; got solver {self.solver} steps {self.steps}",
                              key="solver")


@dataclass
class DiffusionConfig:
    """The diffusion baseline (`objective: ddpm`), Diffusion Policy's defaults: 100 training
    timesteps, squared-cosine schedule, epsilon prediction, predicted samples clipped to [-1, 1];
    sampled with DDPM (all steps) or DDIM (`inference_steps` of them)."""

    num_train_timesteps: int = knob(100, count(1, 100_000))
    beta_start: float = knob(1e-4, Range(lo=0, hi=1, lo_open=True, hi_open=True))
    beta_end: float = knob(0.02, Range(lo=0, hi=1, lo_open=True, hi_open=True))
    beta_schedule: Literal["squaredcos_cap_v2", "linear", "scaled_linear"] = "squaredcos_cap_v2"
    clip_sample: bool = True
    sampler: Literal["ddpm", "ddim"] = "ddpm"
    inference_steps: int = knob(100, count(1, 100_000))

    def validate(self) -> None:
        if not 1 <= self.inference_steps <= self.num_train_timesteps:
            raise ConfigError(f"inference_steps must be in [1, num_train_timesteps = "
                              f"{self.num_train_timesteps}]", key="inference_steps")


@dataclass
class NormalizerConfig:
    action: Literal["limits", "gaussian"] = "limits"
    obs: Literal["limits", "gaussian"] = "limits"
    # a dimension whose range (limits) or std (gaussian) in the training data is below this, in
    # the data's own units, is treated as constant: shifted, never stretched (Diffusion Policy's
    # 1e-4). Raise it when a dimension only jitters in the demonstrations (a simulator's gripper
    # opening that varies by 0.003): stretched to [-1, 1], its slightest change at run time
    # becomes an input far outside anything trained on.
    range_eps: float = knob(1e-4, POSITIVE)  # sefa_data.normalizer.DEFAULT_RANGE_EPS


@dataclass
class TrainingConfig:
    seed: int = knob(42, SEED)
    device: str = "auto"  # auto | cpu | cuda | cuda:N | mps
    # the global batch (DDP splits it across ranks); at most the training windows and what fits
    # in memory, checked against the store by sefa_model/train/limits.py before a run starts
    batch_size: int = knob(256, count(1))
    max_steps: int = knob(5000, count(1, 100_000_000))
    lr: float = knob(1e-4, POSITIVE)  # no upper bound: a diverging training is stopped by the training loop (train/loop.py)
    betas: list[float] = knob(valid=UNIT_OPEN, factory=lambda: [0.95, 0.999])
    eps: float = knob(1e-8, POSITIVE)
    weight_decay: float = knob(1e-6, NONNEGATIVE)
    lr_warmup_steps: int = knob(500, count(0, 100_000_000))
    # the cosine decay's length; None: max_steps. A run may stop part-way along a longer schedule
    # and be the same weights as that longer run's checkpoint at max_steps (the budget curve's).
    lr_decay_steps: int | None = knob(None, count(1, 100_000_000))
    grad_clip: float | None = knob(1.0, POSITIVE)
    ema: bool = True
    ema_power: float = knob(0.75, POSITIVE)
    ema_inv_gamma: float = knob(1.0, POSITIVE)
    ema_max_decay: float = knob(0.9999, UNIT)
    val_every: int = knob(500, count(1))
    val_batches: int = knob(4, count(1, 100_000))
    val_sample_windows: int = knob(64, count(0, 1_000_000))  # windows whose actions are sampled with the solver for val MSE
    checkpoint_every: int = knob(500, count(1))
    keep_every: int | None = knob(None, count(1))  # also keep checkpoints/step_N every this many steps (budget curves)
    log_every: int = knob(50, count(1))
    mixed_precision: bool = True  # bf16 autocast on GPUs that support it; fp32 elsewhere
    # reflow and distillation: keep the initial checkpoint's observation encoder fixed and train
    # on its features, computed once per window (the reference's stored conditioning)
    freeze_encoder: bool = False
    num_workers: int | None = knob(None, count(0, 256))  # loader processes; None: 0 on the CPU, cores - 1 (<= 8) per GPU
    compile: bool = False  # torch.compile the network (opt-in: minutes of compile time)
    wandb: str | None = None  # a Weights & Biases project to log to (needs the wandb package)

    def validate(self) -> None:
        if self.lr_decay_steps is not None and self.lr_decay_steps < self.max_steps:
            raise ConfigError(f"lr_decay_steps ({self.lr_decay_steps}) must be null or at least "
                              f"max_steps ({self.max_steps})", key="lr_decay_steps")
        from sefa_model.distributed import check_device_name

        check_device_name(self.device, key="training.device")

    def warnings(self) -> list[str]:
        """Settings that are valid but silently defeat themselves (training says them at its
        start): a warmup as long as the run never reaches the learning rate it names."""
        out = []
        if self.lr_warmup_steps >= self.max_steps:
            out.append(f"warning: training.lr_warmup_steps ({self.lr_warmup_steps}) is not shorter "
                       f"than training.max_steps ({self.max_steps}): the learning rate never "
                       f"reaches training.lr ({self.lr:g}); set lr_warmup_steps below max_steps "
                       f"(e.g. training.lr_warmup_steps={max(0, self.max_steps // 10)})")
        return out


@dataclass
class TrainConfig:
    dataset: str = "dataset.zarr"
    # flow: the rectified flow that SeFA builds on; ddpm: the diffusion baseline, same network
    objective: Literal["flow", "ddpm"] = "flow"
    # how the policy is trained and sampled (sefa_model/methods: a student's recipe); None: what
    # the objective and flow.t_train say, as before methods existed. Checked, with the settings
    # below, by `sefa_model.methods.method_of`, the one reader of both (and of `objective`)
    method: str | None = None
    # the method's own settings (its `Knobs` dataclass: strict keys and ranges), e.g.
    # `method_config.u_shape_a=3` for rfpp; recorded resolved by the stage that derives the config
    method_config: dict[str, Any] = field(default_factory=dict)
    shape_meta: ShapeMeta = field(default_factory=ShapeMeta)
    policy: PolicyConfig = field(default_factory=PolicyConfig)
    flow: FlowConfig = field(default_factory=FlowConfig)
    diffusion: DiffusionConfig = field(default_factory=DiffusionConfig)
    normalizer: NormalizerConfig = field(default_factory=NormalizerConfig)
    training: TrainingConfig = field(default_factory=TrainingConfig)


def load_train_config(path: str | Path | None = None, overrides: list[str] | None = None
                      ) -> TrainConfig:
    data = load_yaml(path) if path else {}
    data = apply_overrides(data, overrides or [])
    return from_dict(TrainConfig, data, source=str(path) if path else "overrides")


def saved_train_config(data: dict, source: str) -> TrainConfig:
    """A checkpoint's resolved config (config.json's train_config). One written before
    `obs_keys` existed has its observation set in `obs` alone: that set, not the store's."""
    cfg = from_dict(TrainConfig, data, source=source)
    if cfg.shape_meta.obs_keys is None and cfg.shape_meta.obs:
        cfg.shape_meta.obs_keys = list(cfg.shape_meta.obs)
    return cfg


def config_to_dict(cfg: TrainConfig) -> dict:
    return to_dict(cfg)


# The `training` keys that change where, how fast or how verbosely a run is carried out, never
# the weights it trains. The ONE list: the stage runner leaves them out of the cache key (changing
# one reruns nothing; pipelines/stages.py), and a continued run takes them from the current
# settings (train/loop.py). Each with why it cannot change the weights:
UNKEYED_TRAINING = {
    # where: a workspace trained on a laptop's CPU is reused, not retrained, on a GPU server
    "device": "where the run executes",
    # batches are drawn by step (train_batches.batch_indices), not by loader process
    "num_workers": "loader processes only",
    "compile": "torch.compile runs the same network faster",
    "wandb": "where the logs also go",
    "log_every": "how often the loss is logged",
    # validation uses its own seeded generators, and every step reseeds the global RNG first
    # (optimizer_step), so when it runs does not touch training; the last step always
    # validates, so the recorded validation is the same. `best` may be picked among other steps.
    "val_every": "how often validation runs",
    # a resumed run continues bit for bit (tests/sefa_model_tests/test_training.py), so where it may resume
    # from does not matter; the last step always checkpoints
    "checkpoint_every": "how often the checkpoint is saved",
}
# Kept in the key on purpose: val_batches and val_sample_windows (they define the validation
# numbers a run records), keep_every (it decides which checkpoints a run keeps), mixed_precision
# (bf16 trains other weights), and every key that shapes the optimisation.
# Never recorded in a stage's config at all (older manifests do not have them either).
EXECUTION_KEYS = ("device", "num_workers", "wandb")


def cache_key_dict(cfg: TrainConfig) -> dict:
    """A train config as a stage records it: where it runs left out (see UNKEYED_TRAINING for
    what the runner also leaves out of the key)."""
    data = config_to_dict(cfg)
    data["training"] = {k: v for k, v in data["training"].items() if k not in EXECUTION_KEYS}
    if data["training"].get("lr_decay_steps") is None:  # added later: older runs keep their keys
        data["training"].pop("lr_decay_steps", None)
    if data.get("method") is None:  # likewise: a config naming no method keeps its key
        data.pop("method", None)
    if not data.get("method_config"):  # and one whose method has no settings
        data.pop("method_config", None)
    if data["normalizer"].get("range_eps") == NormalizerConfig.range_eps:  # and the normalizer's
        data["normalizer"].pop("range_eps")  # constant-dimension threshold at its default
    if data["policy"].get("resize_shape") is None:  # the same for the camera sizes
        data["policy"].pop("resize_shape", None)
    for spec in data["shape_meta"]["obs"].values():
        if spec.get("resize") is None:
            spec.pop("resize", None)
    meta = data["shape_meta"]
    # obs_keys came with issue 25, which changed what a partial `obs` means: a config whose
    # observation set is the same under both readings (no keys named, or obs_keys naming
    # exactly obs's keys in order) keeps its old key; any other one gets a new key, so a run
    # trained on the old reading (state alone) is never taken for the new one's
    if meta["obs_keys"] is None and not meta["obs"] or meta["obs_keys"] == list(meta["obs"]):
        meta.pop("obs_keys")
    elif meta["obs_keys"] is None:
        meta["obs_keys"] = "every store key"
    return data


def lr_schedule_length(training: dict) -> int:
    """The steps the cosine decay spans (a `training` section as a dict)."""
    return training.get("lr_decay_steps") or training["max_steps"]
