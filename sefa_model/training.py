"""`sefa train`: fit the base rectified-flow policy on a store, single process or under torchrun.

Every random draw of step k (the batch's windows, the noise, t, crops) is derived from
(seed, k) alone. A resumed run therefore replays exactly what an uninterrupted one does, given
the weights, optimizer, scheduler and EMA state saved in the checkpoint; and a DDP run with N
ranks draws the same global batch as a single process and gives each rank its slice of it.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset

from sefa_data.errors import SefaInputError
from sefa_data.normalizer import Normalizer, train_frames
from sefa_data.sampler import SequenceSampler, to_torch
from sefa_data.zarr_store import EpisodeStore
from sefa_model.checkpoint import load_state, load_weights, read_json, write_checkpoint
from sefa_data.config_io import from_dict
from sefa_model.config import TrainConfig, config_to_dict
from sefa_model.distributed import DistContext, bf16_supported, describe, setup
from sefa_model.ema import EMA
from sefa_model.features import cached_window_features
from sefa_model.flow_policy import FlowPolicyModel, lowdim_view, resolve_shapes
from sefa_model.diffusion import ddpm_loss, make_scheduler, sample_timesteps
from sefa_model.rectified_flow import flow_loss, sample_t
from sefa_model.run_log import RunLog
from sefa_model.sampling import sample_chunk

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


# ----------------------------------------------------------------------------- data to tensors


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
        self.normalizer = normalizer
        self.store = store
        # the validation baseline: always predict the training set's mean action
        self.mean_action = train_frames(store, meta.action.key).astype(np.float64).mean(0)

    def fit_normalizer(self) -> Normalizer:
        """Fitted on the training split only, on exactly the values the model will see."""
        meta = self.cfg.shape_meta
        data = {meta.action.key: train_frames(self.store, meta.action.key)}
        modes = {meta.action.key: self.cfg.normalizer.action}
        for key, spec in meta.obs.items():
            if spec.type == "low_dim":
                data[key] = lowdim_view(key, spec, train_frames(self.store, key)[:, None])[:, 0]
                modes[key] = self.cfg.normalizer.obs
        return Normalizer.fit(data, modes)

    def tensors(self, sampler: SequenceSampler, idx: np.ndarray, device: torch.device
                ) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
        """(normalized obs dict, normalized action chunk (B, T, Da)) for windows `idx`."""
        raw = to_torch(sampler.batch(idx), device, self.image_keys)
        return self.obs_tensors(raw), self.normalizer.normalize(
            self.cfg.shape_meta.action.key, raw[self.cfg.shape_meta.action.key])

    def obs_tensors(self, raw: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        obs = {}
        for key, spec in self.cfg.shape_meta.obs.items():
            if spec.type == "rgb":
                obs[key] = raw[key]
            else:
                obs[key] = self.normalizer.normalize(key, lowdim_view(key, spec, raw[key]))
        return obs

    def host_batch(self, sampler: SequenceSampler, idx: np.ndarray) -> dict[str, torch.Tensor]:
        """The raw windows as CPU tensors (images still uint8 HWC): what a loader worker makes."""
        return {k: torch.from_numpy(np.ascontiguousarray(v)) for k, v in sampler.batch(idx).items()}

    def device_obs(self, raw: dict[str, torch.Tensor], device: torch.device) -> dict[str, torch.Tensor]:
        """Host windows -> normalized model inputs on `device`. Copies are non-blocking (from
        pinned memory they overlap the running step) and images cross as uint8, a quarter of
        the bytes, to be converted on the device."""
        moved = {k: raw[k].to(device, non_blocking=True) for k in self.cfg.shape_meta.obs}
        for key in self.image_keys:
            moved[key] = moved[key].permute(0, 1, 4, 2, 3).float().div_(255.0)
        return self.obs_tensors({k: v if k in self.image_keys else v.float() for k, v in moved.items()})


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
                self.data.normalizer.normalize(key, x1), batch["t"].to(device, non_blocking=True))


class CouplingPairs:
    """Reflow and distillation: stored (noise, target) couplings of training windows.

    The training time is the config's `flow.t_train`: "uniform" trains a reflowed flow on them
    (t ~ U[t_eps, 1]); "start" trains the velocity at t = t_eps only, so that one Euler step
    from the noise lands on the target. After `use_features`, a batch carries each window's
    frozen condition instead of its observation.
    """

    def __init__(self, data: PolicyData, path: Path, target: str, kind: str):
        import zarr

        group = zarr.open_group(str(path), mode="r")
        self.noise = group["noise"][:]
        self.target = group[target][:]
        self.window = group["window"][:]
        self.data, self.kind = data, kind
        self.features: torch.Tensor | None = None  # (n_windows_used, D), rows by feature_row
        self.feature_row: np.ndarray | None = None  # training window -> row of `features`
        if data.cfg.objective != "flow":
            raise SefaInputError(f"couplings train a flow, but the config's objective is "
                                 f"'{data.cfg.objective}'", key="objective")
        if self.window.max(initial=-1) >= len(data.train):
            raise SefaInputError(f"couplings refer to window {int(self.window.max())} but the "
                                 f"store has {len(data.train)} training windows", file=str(path))

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


# ----------------------------------------------------------------------------- training


@dataclass
class TrainResult:
    run_dir: str
    steps: int
    train_loss: float | None  # None: no step ran (a resumed run that had already finished)
    val: dict = field(default_factory=dict)
    checkpoint: str = ""


@dataclass
class Callbacks:
    log: Callable[[str], None] = lambda _: None
    on_step: Callable[[int, int, float], None] = lambda step, total, loss: None


def train(cfg: TrainConfig, run_dir: Path, store_path: Path, *, resume: bool = False,
          callbacks: Callbacks | None = None, couplings: dict | None = None,
          init_from: Path | None = None, features_cache: Path | None = None) -> TrainResult:
    """Train a flow policy. By default the base flow on expert windows; with `couplings`
    ({"path", "target": "action"|"target", "kind"}) a reflowed flow or the one-step student
    (`cfg.flow.t_train` says which), starting from the weights and normalizer of checkpoint
    `init_from`; with `training.freeze_encoder` that checkpoint's encoder stays fixed and the
    network trains on its features, computed once per window (and kept in `features_cache`,
    see sefa_model/features.py, so the next stage with the same encoder reads them).

    Under torchrun every rank calls this; rank 0 alone writes (normalizer, logs, checkpoints).
    The host waits for the device only at log, validation and checkpoint steps."""
    cb = callbacks or Callbacks()
    run_dir = Path(run_dir)
    latest = run_dir / "checkpoints" / "latest"
    if resume and (latest / "config.json").exists():
        # the saved config is the single source of truth for a resumed run (but not where it runs)
        device_name = cfg.training.device
        cfg = from_dict(TrainConfig, read_json(latest / "config.json")["train_config"],
                        source=str(latest / "config.json"))
        cfg.training.device = device_name
    elif resume:
        cb.log(f"no checkpoint in {run_dir} to resume from: starting fresh")
        resume = False
    elif latest.exists() and DistContext.from_env().is_main:
        raise SefaInputError("a run already exists here; pass --resume to continue it or --force "
                             "to start over", file=str(run_dir))

    if cfg.training.freeze_encoder and (couplings is None or init_from is None):
        raise SefaInputError("training.freeze_encoder keeps the encoder of the checkpoint a reflow "
                             "or distillation starts from; the base flow trains its encoder",
                             key="training.freeze_encoder")
    ctx, device = setup(cfg.training.device, key="training.device")
    # every checksum, image chunks included: about 1 s for Push-T's 25,650 frames, against
    # minutes of training (a plain open checks presence and sizes; see store_integrity)
    store = EpisodeStore.open(store_path, verify="full")
    cfg = resolve_shapes(cfg, store)
    data = PolicyData(cfg, store, None)
    t_cfg = cfg.training
    if data.split_note and ctx.is_main:
        cb.log(data.split_note)

    if resume:
        data.normalizer = Normalizer.load(latest)
    elif init_from is not None:  # later stages keep the base policy's normalization
        data.normalizer = Normalizer.load(init_from)
        if ctx.is_main:
            run_dir.mkdir(parents=True, exist_ok=True)
    else:
        if ctx.is_main:
            run_dir.mkdir(parents=True, exist_ok=True)
            data.fit_normalizer().save(run_dir)
        ctx.barrier()  # rank 0 fits; every rank reads the same file
        data.normalizer = Normalizer.load(run_dir)

    torch.manual_seed(t_cfg.seed)
    model = FlowPolicyModel(cfg).to(device)
    ema = EMA(model, t_cfg.ema_power, t_cfg.ema_inv_gamma, t_cfg.ema_max_decay) if t_cfg.ema else None
    if t_cfg.freeze_encoder:
        model.obs_encoder.requires_grad_(False)
    optimizer = torch.optim.AdamW([p for p in model.parameters() if p.requires_grad], lr=t_cfg.lr, betas=tuple(t_cfg.betas),
                                  eps=t_cfg.eps, weight_decay=t_cfg.weight_decay)
    scheduler = torch.optim.lr_scheduler.LambdaLR(
        optimizer, cosine_with_warmup(t_cfg.lr_warmup_steps, t_cfg.lr_decay_steps or t_cfg.max_steps))
    pairs = (ExpertPairs(data) if couplings is None else
             CouplingPairs(data, Path(couplings["path"]), couplings["target"], couplings["kind"]))
    if init_from is not None and not resume:
        load_weights(model, init_from / "ema.safetensors" if (init_from / "ema.safetensors").exists()
                     else init_from / "model.safetensors")
        if ema is not None:
            ema = EMA(model, t_cfg.ema_power, t_cfg.ema_inv_gamma, t_cfg.ema_max_decay)
    step = 0
    best = math.inf
    if resume:
        load_weights(model, latest / "model.safetensors")
        if ema is not None:
            load_weights(ema.model, latest / "ema.safetensors")
        state = load_state(latest / "training_state")
        optimizer.load_state_dict(state["optimizer"])
        scheduler.load_state_dict(state["scheduler"])
        step, best = int(state["step"]), float(state["best"])
        cb.log(f"resuming {run_dir} at step {step}")
    model.to(device)
    ema_model = ema.model.to(device) if ema else None
    encoder_note = "trained"
    if t_cfg.freeze_encoder:
        # the initial weights' encoder: on resume the same (it never changes), so the same features
        pairs.use_features(cached_window_features(model, data, pairs.windows(), device,
                                                  features_cache, is_main=ctx.is_main,
                                                  barrier=ctx.barrier, log=cb.log))
        encoder_note = f"frozen: features of {init_from} (eval mode), computed once per window"
    elif couplings is not None:
        encoder_note = f"fine-tuned from {init_from}"
    wrapped = model
    if ctx.distributed:
        wrapped = torch.nn.parallel.DistributedDataParallel(
            model, device_ids=[device.index] if device.type == "cuda" else None)
    forward = torch.compile(wrapped) if t_cfg.compile else wrapped

    if t_cfg.batch_size % ctx.world:
        raise SefaInputError(f"batch_size {t_cfg.batch_size} is not divisible by the "
                             f"{ctx.world} processes", key="training.batch_size")
    local = t_cfg.batch_size // ctx.world
    mine = slice(ctx.rank * local, (ctx.rank + 1) * local)
    autocast = t_cfg.mixed_precision and bf16_supported(device)
    workers = loader_workers(t_cfg.num_workers, device, ctx)
    if ctx.is_main:
        precision = ("bf16 autocast" if autocast else
                     "fp32" + (f" (bf16 is not supported on {device})" if t_cfg.mixed_precision
                               and device.type != "cpu" else ""))
        cb.log(f"training {pairs.kind} on {describe(device)} x{ctx.world}: {len(pairs)} pairs, "
               f"global batch {t_cfg.batch_size} ({local} per process x {ctx.world}), "
               f"{t_cfg.max_steps} steps, {precision}, {workers} loader workers"
               + (", torch.compile" if t_cfg.compile else ""))
    run_log = (RunLog(run_dir, step, wandb_project=t_cfg.wandb, config=config_to_dict(cfg))
               if ctx.is_main else None)
    loss_of = objective_loss(cfg)
    loss_value = math.nan
    val: dict = {}
    # the losses since the last log step, summed on the device: reading them is a host sync
    loss_sum, loss_count = torch.zeros((), device=device), 0

    def checkpoint(name: str) -> None:
        state = {"optimizer": optimizer.state_dict(), "scheduler": scheduler.state_dict(),
                 "step": step, "best": best}
        write_checkpoint(run_dir / "checkpoints" / name,
                         config=_checkpoint_config(cfg, pairs.kind, encoder_note),
                         model=model, ema=ema_model, normalizer=data.normalizer,
                         training_state=state)

    for batch in step_batches(pairs, cfg, step, mine, device, workers):
        model.train()
        torch.manual_seed(step_seed(t_cfg.seed, step, 1))  # random crops draw from the global RNG
        obs, x0, x1, t = pairs.to_device(batch, device)
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=autocast):
            loss = loss_of(lambda x, tt: forward(obs, x, tt), x0, x1, t)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if t_cfg.grad_clip:
            torch.nn.utils.clip_grad_norm_(model.parameters(), t_cfg.grad_clip)
        optimizer.step()
        scheduler.step()
        step += 1
        if ema is not None:
            ema.update(model, step)
        loss_sum += loss.detach().float()
        loss_count += 1
        log_now = step % t_cfg.log_every == 0 or step == t_cfg.max_steps
        val_now = data.valid is not None and (step % t_cfg.val_every == 0 or step == t_cfg.max_steps)
        ckpt_now = step % t_cfg.checkpoint_every == 0 or step == t_cfg.max_steps
        if log_now or val_now or ckpt_now:  # every rank joins the reduction, in step
            loss_value = float(ctx.mean(loss_sum / loss_count))
            loss_sum.zero_()
            loss_count = 0
        if not ctx.is_main:
            continue
        cb.on_step(step, t_cfg.max_steps, loss_value)
        record = None
        if log_now:
            record = {"step": step, "epoch": epoch_of(step - 1, len(pairs), t_cfg.batch_size),
                      "train_loss": loss_value, "lr": scheduler.get_last_lr()[0]}
        if val_now:
            val = validate(ema_model or model, data, cfg, device)
            cb.log(validation_line(step, t_cfg.max_steps, val))
            record = {**(record or {"step": step}), **val}
            if val["val_action_mse"] < best:
                best = val["val_action_mse"]
                checkpoint("best")
        if record is not None:
            run_log.record(record)
        if ckpt_now:
            checkpoint("latest")
            run_log.checkpoint()
        if t_cfg.keep_every and step % t_cfg.keep_every == 0:
            checkpoint(f"step_{step}")
    if run_log is not None:
        run_log.close()
    ctx.barrier()  # the checkpoints are on disk before any rank reads them
    return TrainResult(str(run_dir), step, None if math.isnan(loss_value) else loss_value, val,
                       str(run_dir / "checkpoints" / "latest"))


def _checkpoint_config(cfg: TrainConfig, kind: str, encoder: str = "trained") -> dict:
    if cfg.objective == "ddpm":
        d = cfg.diffusion
        convention = {"diffusion_convention": {
            "prediction": "epsilon", "x_k": "sqrt(abar_k) x1 + sqrt(1 - abar_k) noise",
            "k_train": f"U{{0..{d.num_train_timesteps - 1}}}", "schedule": d.beta_schedule,
            "clip_sample": d.clip_sample}}
    else:
        f = cfg.flow
        t_train = f"U[{f.t_eps:g}, 1]" if f.t_train == "uniform" else f"{f.t_eps:g} (one step)"
        convention = {"flow_convention": {
            "noise_at": 0.0, "data_at": 1.0, "x_t": "t * x1 + (1 - t) * x0", "target": "x1 - x0",
            "t_train": t_train, "t_sample": f"from {f.t_eps:g} to 1",
            "network_time": f"t * {f.time_scale:g}"}}
    return {"kind": kind, "train_config": config_to_dict(cfg), "encoder": encoder, **convention}


# ----------------------------------------------------------------------------- validation


@torch.no_grad()
def validate(model: FlowPolicyModel, data: PolicyData, cfg: TrainConfig, device: torch.device) -> dict:
    """Flow loss on validation windows, and the MSE of sampled action chunks (in action units)
    next to the MSE of always predicting the training set's mean action."""
    model.eval()
    t_cfg, sampler = cfg.training, data.valid
    n = len(sampler)
    loss_of = objective_loss(cfg)
    losses = []
    for b in range(t_cfg.val_batches):
        idx = np.arange(b * t_cfg.batch_size, (b + 1) * t_cfg.batch_size) % n
        gen = step_generator(t_cfg.seed, b, 2)
        obs, x1 = data.tensors(sampler, idx, device)
        x0 = torch.randn(x1.shape, generator=gen).to(device)
        t = draw_time(cfg, len(idx), gen).to(device)
        losses.append(float(loss_of(lambda x, tt: model(obs, x, tt), x0, x1, t)))
        if (b + 1) * t_cfg.batch_size >= n:
            break
    idx = np.linspace(0, n - 1, min(n, t_cfg.val_sample_windows)).astype(int)
    obs, x1 = data.tensors(sampler, idx, device)
    key = cfg.shape_meta.action.key
    cond = model.encode(obs)
    x0 = torch.randn(x1.shape, generator=step_generator(t_cfg.seed, 0, 3)).to(device)
    result = sample_chunk(model, cfg, cond, x0, generator=torch.Generator(device).manual_seed(t_cfg.seed))
    pred = data.normalizer.unnormalize(key, result.x)
    truth = data.normalizer.unnormalize(key, x1)
    mean_action = torch.as_tensor(data.mean_action, device=device, dtype=truth.dtype)
    return {"val_loss": float(np.mean(losses)),
            "val_action_mse": float(torch.mean((pred - truth) ** 2)),
            "val_mean_action_mse": float(torch.mean((mean_action - truth) ** 2)),
            "val_nfe": result.nfe}


def validation_line(step: int, total: int, val: dict) -> str:
    """Validation as it is computed, next to the mean-action baseline it must beat."""
    ratio = val["val_action_mse"] / max(val["val_mean_action_mse"], 1e-30)
    verdict = ("WORSE than always predicting the mean action" if ratio >= 1 else
               f"{ratio:.0%} of the mean action's")
    return (f"validation at step {step}/{total}: action MSE {val['val_action_mse']:.4g} vs mean "
            f"action {val['val_mean_action_mse']:.4g} ({verdict}), val loss "
            f"{val['val_loss']:.4g}, NFE {val['val_nfe']}")
