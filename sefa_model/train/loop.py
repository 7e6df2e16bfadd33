"""`sefa train`: fit a flow policy on a store, single process or under torchrun, in the manner of
nanoGPT's loop: build the training state, restore it, then one loop with explicit DDP, autocast,
batches prefetched by the loader, and the host waiting for the device only at log steps.

By default the base flow on expert windows; with `couplings` (a `PairSource`) a reflowed flow or
the one-step student (`cfg.flow.t_train` says which), starting from the weights and normalizer of
checkpoint `init_from`. What each step fits and how its batch is drawn: `sefa_model.train.batches`.
"""

from __future__ import annotations

import contextlib
import math
import time
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from sefa_data.errors import NonFiniteError, SefaInputError
from sefa_data.normalizer import Normalizer
from sefa_data.store.journal import fault_point
from sefa_data.store.zarr_store import EpisodeStore
from sefa_model.policy.checkpoint import (load_state, load_weights, open_checkpoint, open_policy,
                                   write_checkpoint)
from sefa_model.config import UNKEYED_TRAINING, TrainConfig, config_to_dict, saved_train_config
from sefa_model.data.couplings import PairSource
from sefa_model.train.device_batches import resident_batches
from sefa_model.distributed import (DistContext, bf16_supported, busy_cpu_note, describe,
                                    load_average, setup, threads_given)
from sefa_model.train.threads import measured_threads
from sefa_model.train.ema import EMA
from sefa_model.progress import RateMeter
from sefa_model.data.features import cached_window_features
from sefa_model.policy.model import FlowPolicyModel, resolve_shapes
from sefa_model.data.windows import PolicyData
from sefa_model.train.run_log import RunLog
from sefa_model.flow.solvers import SolverFailed
from sefa_model.methods import StepCalls, Times, method_of
from sefa_model.train.batches import (CouplingPairs, ExpertPairs, cosine_with_warmup, epoch_of,
                                      loader_workers, step_batches, step_generator, step_seed,
                                      yardstick)


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


@dataclass
class TrainState:
    """Everything a step reads or changes, and everything a checkpoint holds."""

    cfg: TrainConfig
    run_dir: Path
    ctx: DistContext
    device: torch.device
    data: PolicyData
    pairs: ExpertPairs | CouplingPairs
    model: FlowPolicyModel
    ema: EMA | None
    optimizer: torch.optim.Optimizer
    scheduler: torch.optim.lr_scheduler.LRScheduler
    step: int = 0
    best: float = math.inf
    encoder_note: str = "trained"
    # the frozen initial policy, for a method whose loss calls it (a student distilling it)
    teacher: FlowPolicyModel | None = None

    @property
    def eval_model(self) -> FlowPolicyModel:
        return self.ema.model if self.ema is not None else self.model

    def checkpoint(self, name: str) -> None:
        """Write checkpoint `name`; weights that are not finite stop the run instead."""
        state = {"optimizer": self.optimizer.state_dict(), "scheduler": self.scheduler.state_dict(),
                 "step": self.step, "best": self.best}
        try:
            write_checkpoint(self.run_dir / "checkpoints" / name,
                             config=_checkpoint_config(self.cfg, self.pairs.kind, self.encoder_note),
                             model=self.model, ema=self.ema.model if self.ema else None,
                             normalizer=self.data.normalizer, training_state=state,
                             processor=self.data.processor.describe())
        except NonFiniteError as e:
            raise diverged(self, e.what) from None


# ----------------------------------------------------------------------------- the loop


def train(cfg: TrainConfig, run_dir: Path, store_path: Path, *, resume: bool = False,
          callbacks: Callbacks | None = None, couplings: PairSource | None = None,
          init_from: Path | None = None, features_cache: Path | None = None,
          extend: bool = False) -> TrainResult:
    """Train a flow policy (see the module docstring). With `training.freeze_encoder` the
    encoder of `init_from` stays fixed and the network trains on its features, computed once per
    window and kept in `features_cache` (sefa_model/data/features.py).

    A resumed run trains with its saved config; with `extend` (the stage runner's builds) it
    takes this cfg's length and bookkeeping keys (config.UNKEYED_TRAINING) instead: the runner
    checked that the rest is the same, and a finished shorter run goes on to cfg's max_steps.

    Under torchrun every rank calls this; rank 0 alone writes (normalizer, logs, checkpoints)."""
    cb = callbacks or Callbacks()
    s = prepare(cfg, Path(run_dir), store_path, resume, couplings, init_from, features_cache, cb,
                extend)
    t_cfg, ctx, device = s.cfg.training, s.ctx, s.device
    forward = _wrap(s.model, ctx, device, t_cfg.compile)
    mine = _rank_slice(t_cfg.batch_size, ctx)
    autocast = t_cfg.mixed_precision and bf16_supported(device)
    # on CUDA the data on the device where it fits (sefa_model/train/device_batches.py), else the loader
    resident = resident_batches(s.pairs, s.cfg, s.step, mine, device)
    workers = 0 if resident is not None else loader_workers(t_cfg.num_workers, device, ctx)
    if ctx.is_main:
        cb.log(_start_line(s, autocast, workers) + (", data on the device" if resident else ""))
        for warning in t_cfg.warnings():
            cb.log(warning)
        busy = busy_cpu_note(device, torch.get_num_threads(), load_average(), os.cpu_count())
        if busy and threads_given():  # else the cost probe measures one thread too
            cb.log(busy)
    run_log = RunLog(s.run_dir, s.step, wandb_project=t_cfg.wandb,
                     config=config_to_dict(s.cfg)) if ctx.is_main else None
    # closed at the end; on an error (a Ctrl-C in the cost probe too) its writers stop before
    # the caller removes the unfinished run folder they write into (run_log.py)
    with run_log or contextlib.nullcontext():
        if ctx.is_main and device.type == "cpu" and ctx.world == 1 and s.step < t_cfg.max_steps:
            announce_cost(s, forward, autocast, cb)
        loss_value, val = math.nan, {}
        # the measured cost, said once, past the warm-up (sefa_model/progress.py)
        meter, said = RateMeter(s.step, time.perf_counter(), t_cfg.max_steps), False
        # the losses since the last log step, summed on the device: reading them is a host sync
        loss_sum, loss_count = torch.zeros((), device=device), 0
        for batch in resident or step_batches(s.pairs, s.cfg, s.step, mine, device, workers):
            loss_sum += optimizer_step(s, forward, batch, autocast)
            loss_count += 1
            log_now, val_now, ckpt_now = _due(s)
            if log_now or val_now or ckpt_now:  # every rank joins the reduction, in step
                loss_value = float(ctx.mean(loss_sum / loss_count))
                if not math.isfinite(loss_value):  # every rank sees the same mean and stops
                    raise diverged(s, f"the training loss is {loss_value} (mean of the last "
                                      f"{loss_count} steps)")
                loss_sum.zero_()
                loss_count = 0
            if not ctx.is_main:
                continue
            if not said:
                meter.add(s.step, time.perf_counter())
                said = measured_enough(meter)
                if said and s.step < t_cfg.max_steps:
                    cb.log(measured_line(s, meter))
            cb.on_step(s.step, t_cfg.max_steps, loss_value)
            record = _log_record(s, loss_value) if log_now else None
            if val_now:
                val = checked_validation(s)
                cb.log(validation_line(s.step, t_cfg.max_steps, val))
                record = {**(record or {"step": s.step}), **val}
                if val["val_action_mse"] < s.best:
                    s.best = val["val_action_mse"]
                    s.checkpoint("best")
            if record is not None:
                run_log.record(record)
            if ckpt_now:
                s.checkpoint("latest")
                run_log.checkpoint()
                fault_point("train.checkpointed")  # tests: a Ctrl-C right after a checkpoint
            if t_cfg.keep_every and s.step % t_cfg.keep_every == 0:
                s.checkpoint(f"step_{s.step}")
    ctx.barrier()  # the checkpoints are on disk before any rank reads them
    return TrainResult(str(s.run_dir), s.step, None if math.isnan(loss_value) else loss_value, val,
                       str(s.run_dir / "checkpoints" / "latest"))


PROBE_WINDOWS = 8  # the first batch the cost estimate times before the first step
PROBE_SECONDS = 1.0  # it doubles the batch up to the global one while a call takes less
PROBE_CALLS = 30  # at most this many calls of a cheap whole batch, over PROBE_SECONDS
CPU_SIZED_SECONDS = 600  # a run longer than this on the CPU says what a CPU-sized one is
CAMERA_PRESET = "--preset lerobot_camera_cpu"  # pipelines/presets.py: a name that works anywhere


def estimate_step_seconds(s: TrainState, forward, autocast: bool) -> tuple[float, str]:
    """(seconds per optimizer step, how they were measured), in seconds before the first step
    (whose batch may take minutes on a CPU): this step's windows fetched and run forward and
    backward, one untimed call first (it pays one-time costs: allocations, lazy
    initialisation), then batches of PROBE_WINDOWS, twice as many, ... up to the global batch
    or until a call takes PROBE_SECONDS. A whole batch timed gives the step (its mean over
    about PROBE_SECONDS more); else the cost per window between the two largest batches timed
    is extrapolated to the global batch (small batches cost more per window than large ones,
    so a whole batch is timed whenever it is cheap). Then the update (`update_seconds`). The
    weights, the optimizer and the RNG are left as they were: the gradients are discarded by
    the first step's zero_grad."""
    from sefa_model.train.batches import StepBatches

    t_cfg = s.cfg.training
    rng = torch.get_rng_state()
    s.model.train()

    def timed(n: int) -> float:
        started = time.perf_counter()
        batch = StepBatches(s.pairs, t_cfg.seed, n, slice(0, n))[s.step]
        obs, x0, x1, times = s.pairs.to_device(batch, s.device)
        with torch.autocast(s.device.type, dtype=torch.bfloat16, enabled=autocast):
            loss = s.pairs.method.loss(s.cfg, step_calls(s, forward, obs), x0, x1, times)
        loss.backward()
        return time.perf_counter() - started

    full = t_cfg.batch_size
    n = min(PROBE_WINDOWS, full)
    timed(n)
    sizes = {n: timed(n)}
    while n < full and sizes[n] < PROBE_SECONDS:
        n = min(2 * n, full)
        sizes[n] = timed(n)
    if n == full:
        # a cheap batch: its mean over PROBE_SECONDS (the first call at this size left out), so
        # that the time a busy machine's other jobs take is in it as it will be in the steps
        # (no more calls than the run has steps: a smoke run of a few steps is not probed longer
        # than it runs)
        calls = [timed(n) for _ in range(min(PROBE_CALLS, int(PROBE_SECONDS / sizes[n]),
                                             t_cfg.max_steps - s.step))]
        per_step = float(np.mean(calls)) if calls else sizes[n]
        how = f"a batch of {full} timed" + (f" {len(calls)} times" if len(calls) > 1 else "")
    else:
        small, big = sorted(sizes)[-2:] if len(sizes) > 1 else (n, n)
        per_window = max(0.0, (sizes[big] - sizes[small]) / (big - small)) if big > small else \
            sizes[big] / big
        per_step = sizes[big] + per_window * (full - big)
        how = f"batches of up to {big} windows timed, extrapolated"
    per_step += update_seconds(s)
    s.optimizer.zero_grad(set_to_none=True)
    torch.set_rng_state(rng)
    return per_step, how


def announce_cost(s: TrainState, forward, autocast: bool, cb: Callbacks) -> None:
    """Say what the run will cost before its first step, at the faster of torch's threads and
    one when nobody chose a count (sefa_model/train/threads.py), which the run then keeps."""
    how = []  # how the last probe measured (a whole batch, or extrapolated)

    def probe() -> float:
        per_step, text = estimate_step_seconds(s, forward, autocast)
        how.append(text)
        return per_step

    per_step, threads = measured_threads(probe, s.device,
                                         steps=s.cfg.training.max_steps - s.step)
    for line in filter(None, (threads, cost_line(s, (per_step, how[-1])))):
        cb.log(line)


def update_seconds(s: TrainState) -> float:
    """Seconds of a step's update (AdamW and the EMA, a sixth of a small MLP's step), timed on
    copies: the run's weights, optimizer state and EMA are not touched (the copies take the
    gradients the probe left)."""
    import copy

    optimizer = copy.deepcopy(s.optimizer)  # on its own copies of the weights
    for group, copied in zip(s.optimizer.param_groups, optimizer.param_groups):
        for p, c in zip(group["params"], copied["params"]):
            c.grad = None if p.grad is None else p.grad.detach().clone()
    ema = copy.deepcopy(s.ema) if s.ema is not None else None
    times = []
    for _ in range(3):  # the first allocates AdamW's state
        started = time.perf_counter()
        optimizer.step()
        if ema is not None:
            ema.update(s.model, s.step + 1)
        times.append(time.perf_counter() - started)
    return float(np.median(times[1:]))


def cost_line(s: TrainState, estimate: tuple[float, str]) -> str:
    """What the run will cost, said before it starts, and what a CPU-sized run is when it is
    long."""
    t_cfg = s.cfg.training
    per_step, how = estimate
    left = t_cfg.max_steps - s.step
    total = left * per_step
    text = (f"cost: {left} steps of batch {t_cfg.batch_size}, about {per_step:.3g} s per step "
            f"here ({how}), ETA about {_duration(total)}")
    if total > CPU_SIZED_SECONDS:
        # the camera preset, unless this is already its size (the tiny encoder)
        cameras = (any(spec.type == "rgb" for spec in s.cfg.shape_meta.obs.values())
                   and s.cfg.policy.image_encoder != "tiny")
        text += ("; a CPU-sized run: " + (f"`sefa train {CAMERA_PRESET}` (cameras: tiny "
                                          "encoder, 64x64, small batch) or " if cameras else "")
                 + "fewer training.max_steps or a smaller training.batch_size, or a GPU "
                 "(--device cuda)")
    return text


# the measured cost is said once this many seconds past the warm-up were timed, or a tenth of
# the run (at least two steps), whichever comes first
MEASURE_SECONDS = 10.0


def measured_enough(meter: RateMeter) -> bool:
    measured = meter.measured()
    if measured is None:
        return False
    rate, first, last = measured
    steps = last - first
    return steps / rate >= MEASURE_SECONDS or steps >= max(2, 0.1 * (meter.total - meter.start[1]))


def measured_line(s: TrainState, meter: RateMeter) -> str:
    rate, first, last = meter.measured()
    left = s.cfg.training.max_steps - s.step
    start, first, last = int(meter.start[1]), int(first), int(last)
    warmup = f"step {first}" if first == start + 1 else f"steps {start + 1}-{first}"
    return (f"measured: {1 / rate:.3g} s per step over steps {first + 1}-{last} ({warmup} left "
            f"out: warm-up), ETA about {_duration(left / rate)} for the {left} steps left")


def _duration(seconds: float) -> str:
    seconds = int(round(seconds))
    h, rest = divmod(seconds, 3600)
    return f"{h}:{rest // 60:02d}:{rest % 60:02d}" if h else f"{rest // 60}:{rest % 60:02d}"


def step_calls(s: TrainState, forward, obs) -> StepCalls:
    """The network as the method's loss calls it, the observation (or frozen condition) bound:
    with gradients through `forward` (DDP, compile), without them on the same weights, and the
    frozen teacher. A call without d is exactly the plain call (no step input involved)."""
    def f(x, t, d=None):
        return forward(obs, x, t) if d is None else forward(obs, x, t, d)

    def target(x, t, d=None):
        return s.model(obs, x, t, d)

    teacher = None
    if s.teacher is not None:
        cond = obs if torch.is_tensor(obs) else s.teacher.encode(obs)
        teacher = lambda x, t, d=None: s.teacher.velocity(x, t, cond)  # noqa: E731

    def rows(mask: torch.Tensor) -> StepCalls:
        part = obs[mask] if torch.is_tensor(obs) else {k: v[mask] for k, v in obs.items()}
        return step_calls(s, forward, part)

    return StepCalls(f, target, teacher, rows)


def optimizer_step(s: TrainState, forward, batch: dict, autocast: bool) -> torch.Tensor:
    """One step on this rank's batch: the method's loss, backward, clip, AdamW, schedule, EMA.
    Returns the detached loss, still on the device."""
    t_cfg = s.cfg.training
    s.model.train()
    torch.manual_seed(step_seed(t_cfg.seed, s.step, 1))  # random crops draw from the global RNG
    obs, x0, x1, times = s.pairs.to_device(batch, s.device)
    with torch.autocast(s.device.type, dtype=torch.bfloat16, enabled=autocast):
        loss = s.pairs.method.loss(s.cfg, step_calls(s, forward, obs), x0, x1, times)
    s.optimizer.zero_grad(set_to_none=True)
    loss.backward()
    if t_cfg.grad_clip:
        torch.nn.utils.clip_grad_norm_(s.model.parameters(), t_cfg.grad_clip)
    s.optimizer.step()
    s.scheduler.step()
    s.step += 1
    if s.ema is not None:
        s.ema.update(s.model, s.step)
    return loss.detach().float()


def _due(s: TrainState) -> tuple[bool, bool, bool]:
    """(log, validate, checkpoint) at this step; the last step does all three."""
    t_cfg, step = s.cfg.training, s.step
    last = step == t_cfg.max_steps
    return (step % t_cfg.log_every == 0 or last,
            s.data.valid is not None and (step % t_cfg.val_every == 0 or last),
            step % t_cfg.checkpoint_every == 0 or last)


def _log_record(s: TrainState, loss_value: float) -> dict:
    return {"step": s.step, "epoch": epoch_of(s.step - 1, len(s.pairs), s.cfg.training.batch_size),
            "train_loss": loss_value, "lr": s.scheduler.get_last_lr()[0]}


# ----------------------------------------------------------------------------- the state


def prepare(cfg: TrainConfig, run_dir: Path, store_path: Path, resume: bool,
            couplings: PairSource | None, init_from: Path | None, features_cache: Path | None,
            cb: Callbacks, extend: bool = False) -> TrainState:
    """The state the loop starts from: built, then restored (a resumed run) or started from
    `init_from`'s weights (reflow, distillation), the encoder frozen where asked."""
    if couplings is not None and not isinstance(couplings, PairSource):
        raise TypeError(f"couplings must be a sefa_model.data.couplings.PairSource, got "
                        f"{type(couplings).__name__}")
    cfg, resume = _run_config(cfg, run_dir, resume, cb, extend)
    if init_from is not None and not resume:
        # checked before its normalizer or weights are read: what a reflow or distillation reads
        # of it (config, weights, normalizer, processor), as for any policy that runs, so a base
        # copied without its optimizer state (a deployed checkpoint) can be distilled
        open_policy(init_from)
    s = build_state(cfg, run_dir, store_path, resume=resume, couplings=couplings,
                    init_from=init_from, cb=cb)
    if resume:
        restore(s, cb, extend)
    elif init_from is not None:
        start_from(s, init_from)
    freeze_encoder(s, init_from, features_cache, cb)
    if s.pairs.method.needs_teacher:
        s.teacher = load_teacher(s, init_from)
    return s


def load_teacher(s: TrainState, init_from: Path | None) -> FlowPolicyModel:
    """The frozen policy a student distils: `init_from` as it is (its own config: no step
    input), evaluated without gradients, EMA weights."""
    if init_from is None:
        raise SefaInputError(f"method {s.pairs.method.name} distils a base flow: it needs the "
                             f"checkpoint to start from", key="method")
    path, meta, weights = open_policy(init_from)
    teacher = FlowPolicyModel(resolve_shapes(saved_train_config(
        meta["train_config"], source=str(path / "config.json")), s.data.store))
    load_weights(teacher, weights)
    return teacher.to(s.device).eval().requires_grad_(False)


def _run_config(cfg: TrainConfig, run_dir: Path, resume: bool, cb: Callbacks,
                extend: bool = False) -> tuple[TrainConfig, bool]:
    """The config to run: a resumed run's own saved config (but not where it runs). The
    checkpoint resumed from is checked whole (checksums, config, finite weights) first."""
    latest = run_dir / "checkpoints" / "latest"
    if resume and (latest / "config.json").exists():
        current = cfg.training
        _, meta = open_checkpoint(latest)
        cfg = saved_train_config(meta["train_config"], source=str(latest / "config.json"))
        cfg.training.device = current.device
        for key in (*UNKEYED_TRAINING, "max_steps", "lr_decay_steps") if extend else ():
            setattr(cfg.training, key, getattr(current, key))
        return cfg, True
    if resume:
        cb.log(f"no checkpoint in {run_dir} to resume from: starting fresh")
        return cfg, False
    if latest.exists() and DistContext.from_env().is_main:
        raise SefaInputError("a run already exists here; pass --resume to continue it or --force "
                             "to start over", file=str(run_dir))
    return cfg, False


def build_state(cfg: TrainConfig, run_dir: Path, store_path: Path, *, resume: bool,
                couplings: PairSource | None, init_from: Path | None, cb: Callbacks) -> TrainState:
    """The data, its normalizer, a freshly initialised model, its EMA and optimizer."""
    if cfg.training.freeze_encoder and init_from is None:
        raise SefaInputError("training.freeze_encoder keeps the encoder of the checkpoint a reflow "
                             "or distillation starts from; the base flow trains its encoder",
                             key="training.freeze_encoder")
    ctx, device = setup(cfg.training.device, key="training.device")
    # every checksum, image chunks included: about 1 s for Push-T's 25,650 frames, against
    # minutes of training (a plain open checks presence and sizes; see sefa_data.store.integrity)
    store = EpisodeStore.open(store_path, verify="full")
    cfg = resolve_shapes(cfg, store)
    data = PolicyData(cfg, store, None)
    if data.split_note and ctx.is_main:
        cb.log(data.split_note)
    data.use_normalizer(_normalizer(data, run_dir, resume, init_from, ctx))
    t_cfg = cfg.training
    torch.manual_seed(t_cfg.seed)
    model = FlowPolicyModel(cfg).to(device)
    ema = EMA(model, t_cfg.ema_power, t_cfg.ema_inv_gamma, t_cfg.ema_max_decay) if t_cfg.ema else None
    if t_cfg.freeze_encoder:
        model.obs_encoder.requires_grad_(False)
    optimizer = torch.optim.AdamW([p for p in model.parameters() if p.requires_grad], lr=t_cfg.lr,
                                  betas=tuple(t_cfg.betas), eps=t_cfg.eps,
                                  weight_decay=t_cfg.weight_decay, **adamw_kernel(device))
    scheduler = torch.optim.lr_scheduler.LambdaLR(
        optimizer, cosine_with_warmup(t_cfg.lr_warmup_steps, t_cfg.lr_decay_steps or t_cfg.max_steps))
    pairs = ExpertPairs(data) if couplings is None else CouplingPairs(data, couplings)
    if t_cfg.batch_size % ctx.world:
        raise SefaInputError(f"batch_size {t_cfg.batch_size} is not divisible by the "
                             f"{ctx.world} processes", key="training.batch_size")
    return TrainState(cfg, run_dir, ctx, device, data, pairs, model, ema, optimizer, scheduler)


def _normalizer(data: PolicyData, run_dir: Path, resume: bool, init_from: Path | None,
                ctx: DistContext) -> Normalizer:
    """A resumed run's own; later stages keep the base policy's; else fitted by rank 0."""
    if resume:
        return Normalizer.load(run_dir / "checkpoints" / "latest")
    if ctx.is_main:
        run_dir.mkdir(parents=True, exist_ok=True)
    if init_from is not None:
        return Normalizer.load(init_from)
    if ctx.is_main:
        data.fit_normalizer().save(run_dir)
    ctx.barrier()  # rank 0 fits; every rank reads the same file
    return Normalizer.load(run_dir)


def start_from(s: TrainState, init_from: Path) -> None:
    """A reflow or distillation starts from `init_from`'s (EMA) weights, its EMA anew. A
    student with a step input starts with that embedding at zero (it adds nothing yet)."""
    _, _, weights = open_policy(init_from)
    load_weights(s.model, weights, new_ok=("head.step_encoder.",) if s.pairs.method.step_input else ())
    if s.ema is not None:
        t_cfg = s.cfg.training
        s.ema = EMA(s.model, t_cfg.ema_power, t_cfg.ema_inv_gamma, t_cfg.ema_max_decay)
        s.ema.model.to(s.device)


def restore(s: TrainState, cb: Callbacks, extend: bool = False) -> None:
    """Continue an interrupted run: weights, EMA, optimizer, schedule, step and best. With
    `extend` the schedule may be another length: the next step's learning rate is this one's."""
    latest = s.run_dir / "checkpoints" / "latest"
    load_weights(s.model, latest / "model.safetensors")
    if s.ema is not None:
        load_weights(s.ema.model, latest / "ema.safetensors")
    state = load_state(latest / "training_state")
    for group in state["optimizer"]["param_groups"]:
        # the saved groups name the kernel of the device they ran on: this device's instead,
        # before loading, which places the step counts where that kernel wants them
        group.update(adamw_kernel(s.device))
    s.optimizer.load_state_dict(state["optimizer"])
    s.scheduler.load_state_dict(state["scheduler"])
    s.step, s.best = int(state["step"]), float(state["best"])
    if extend:  # the same numbers when the schedule is the same
        sched = s.scheduler
        sched._last_lr = [base * f(sched.last_epoch) for base, f in zip(sched.base_lrs,
                                                                        sched.lr_lambdas)]
        for group, lr in zip(s.optimizer.param_groups, sched._last_lr):
            group["lr"] = lr
    cb.log(f"resuming {s.run_dir} at step {s.step}")


def freeze_encoder(s: TrainState, init_from: Path | None, features_cache: Path | None,
                   cb: Callbacks) -> None:
    """With a frozen encoder the pairs carry each window's condition, computed once; the
    initial weights' encoder (on resume the same: it never changes), so the same features."""
    if s.cfg.training.freeze_encoder:
        s.pairs.use_features(cached_window_features(s.model, s.data, s.pairs.windows(), s.device,
                                                    features_cache, is_main=s.ctx.is_main,
                                                    barrier=s.ctx.barrier, log=cb.log))
        s.encoder_note = f"frozen: features of {init_from} (eval mode), computed once per window"
    elif isinstance(s.pairs, CouplingPairs) or init_from is not None:
        s.encoder_note = f"fine-tuned from {init_from}"


def adamw_kernel(device: torch.device) -> dict:
    """AdamW's implementation: on CUDA the fused kernel (a few launches per step instead of a
    dozen per parameter tensor); elsewhere torch's default (on the CPU the per-tensor loop,
    whose numbers every CPU run and golden test has)."""
    return {"fused": True, "foreach": None} if device.type == "cuda" else {"fused": None,
                                                                        "foreach": None}


def _wrap(model: FlowPolicyModel, ctx: DistContext, device: torch.device, compile: bool):
    """The module the step calls: DDP across ranks, then torch.compile when asked. On one GPU
    in "reduce-overhead" mode: forward and backward replay as CUDA graphs (shapes are static:
    every step has the same batch), so that a small network's step stops paying one kernel
    launch per op. Opt-in, as before: compiling costs tens of seconds to minutes, which short
    runs do not repay. Under DDP the default mode (its bucket hooks split the graph)."""
    wrapped = model
    if ctx.distributed:
        wrapped = torch.nn.parallel.DistributedDataParallel(
            model, device_ids=[device.index] if device.type == "cuda" else None)
    if not compile:
        return wrapped
    graphs = device.type == "cuda" and not ctx.distributed
    return torch.compile(wrapped, mode="reduce-overhead" if graphs else None)


def _rank_slice(batch_size: int, ctx: DistContext) -> slice:
    local = batch_size // ctx.world
    return slice(ctx.rank * local, (ctx.rank + 1) * local)


def _start_line(s: TrainState, autocast: bool, workers: int) -> str:
    t_cfg, device, world = s.cfg.training, s.device, s.ctx.world
    precision = ("bf16 autocast" if autocast else
                 "fp32" + (f" (bf16 is not supported on {device})" if t_cfg.mixed_precision
                           and device.type != "cpu" else ""))
    return (f"training {s.pairs.kind} on {describe(device)} x{world}: {len(s.pairs)} pairs, "
            f"global batch {t_cfg.batch_size} ({t_cfg.batch_size // world} per process x {world}), "
            f"{t_cfg.max_steps} steps, {precision}, {workers} loader workers"
            + (", torch.compile" if t_cfg.compile else ""))


def _checkpoint_config(cfg: TrainConfig, kind: str, encoder: str = "trained") -> dict:
    return {"kind": kind, "train_config": config_to_dict(cfg), "encoder": encoder,
            **method_of(cfg).convention(cfg)}


def diverged(s: TrainState, what: str) -> NonFiniteError:
    """The one line a diverged run stops with: the step, what was seen, what to change. Nothing
    from it is published (checkpoints refuse non-finite weights; the stage fails)."""
    return NonFiniteError(f"training diverged at step {s.step} of {s.cfg.training.max_steps}: "
                          f"{what}; nothing from this run is published (lower training.lr, now "
                          f"{s.cfg.training.lr:g}, or check the data)")


# ----------------------------------------------------------------------------- validation


def checked_validation(s: TrainState) -> dict:
    """validate() on the EMA (or raw) model, stopping the run where its samples are not finite
    or the ODE cannot be solved (a diverged network, not a solver problem)."""
    try:
        val = validate(s.eval_model, s.data, s.cfg, s.device)
    except SolverFailed as e:
        raise diverged(s, f"validation's ODE solve failed ({str(e).split(';')[0]})") from None
    bad = [k for k, v in val.items() if isinstance(v, float) and not math.isfinite(v)]
    if bad:
        raise diverged(s, f"validation's {bad[0]} is {val[bad[0]]}")
    return val


@torch.no_grad()
def validate(model: FlowPolicyModel, data: PolicyData, cfg: TrainConfig, device: torch.device) -> dict:
    """Flow loss on validation windows, and the MSE of sampled action chunks (in action units)
    next to the MSE of always predicting the training set's mean action: the sampled
    validation of sefa_model/eval/validation.py, which `sefa eval --offline` shares."""
    from sefa_model.eval.validation import action_errors, sample_windows

    model.eval()
    t_cfg, sampler = cfg.training, data.valid
    n = len(sampler)
    method = yardstick(cfg)
    losses = []
    for b in range(t_cfg.val_batches):
        idx = np.arange(b * t_cfg.batch_size, (b + 1) * t_cfg.batch_size) % n
        gen = step_generator(t_cfg.seed, b, 2)
        obs, x1 = data.tensors(sampler, idx, device)
        x0 = torch.randn(x1.shape, generator=gen).to(device)
        t = method.draw(cfg, len(idx), gen).t.to(device)
        calls = StepCalls(lambda x, tt, d=None: model(obs, x, tt))
        losses.append(float(method.loss(cfg, calls, x0, x1, Times(t))))
        if (b + 1) * t_cfg.batch_size >= n:
            break
    chunks = sample_windows(model, data, sampler, t_cfg.val_sample_windows, 1, t_cfg.seed, device)
    errors = action_errors(chunks, data)
    return {"val_loss": float(np.mean(losses)),
            "val_action_mse": errors["action_mse"],
            "val_mean_action_mse": errors["mean_action_mse"],
            "val_nfe": chunks.nfe}


def validation_line(step: int, total: int, val: dict) -> str:
    """Validation as it is computed, next to the mean-action baseline it must beat."""
    ratio = val["val_action_mse"] / max(val["val_mean_action_mse"], 1e-30)
    verdict = ("WORSE than always predicting the mean action" if ratio >= 1 else
               f"{ratio:.0%} of the mean action's")
    return (f"validation at step {step}/{total}: action MSE {val['val_action_mse']:.4g} vs mean "
            f"action {val['val_mean_action_mse']:.4g} ({verdict}), val loss "
            f"{val['val_loss']:.4g}, NFE {val['val_nfe']}")
