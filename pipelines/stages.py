"""The SeFA stages of a workspace, as cached runner stages.

    WORKSPACE/dataset.zarr        sefa ingest (cached by each input's sha256)
    WORKSPACE/train/              the base rectified flow                 sefa train
    WORKSPACE/reflow/iter_1/      couplings of the base flow              sefa reflow --iters N
    WORKSPACE/reflow/iter_k/      a reflowed flow trained on iter_{k-1}'s couplings, and its couplings
    WORKSPACE/align/              the selectively aligned couplings       sefa align --eps E
    WORKSPACE/distill/            the one-step policy                     sefa distill [--no-align]

Each stage's config is its fully resolved settings; its inputs are the store (a file
fingerprint) and its upstream artifacts (manifest hashes), so changing `--eps` reruns align and
distill only. The stage settings of a workspace live in WORKSPACE/sefa.yaml (written by the
commands from their flags) so that bare commands chain.

Where a stage runs (`device`, loader workers, the number of torchrun processes) is not part of
its cache key: a workspace trained on a laptop's CPU is reused, not retrained, on a GPU server.
The device is `--device` of the command, else `device:` in sefa.yaml, else the train config's
`training.device`, else auto.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

import yaml

from pipelines.runner import Stage, Workspace, run_pipeline
from sefa_data import atomic
from sefa_data.config_io import apply_overrides, from_dict, load_yaml
from sefa_model.config import TrainConfig, cache_key_dict, config_to_dict

PIPELINE_FILE = "sefa.yaml"
STORE = "dataset.zarr"


@dataclass
class ReflowStageConfig:
    iters: int = 1
    samples_per_window: int = 10
    solver: str = "rk45"
    rtol: float = 1e-5
    atol: float = 1e-5
    batch_windows: int = 256
    max_windows: int | None = None
    seed: int = 0
    train_overrides: list[str] = field(default_factory=list)  # for the reflowed flows (iter >= 2)
    # align every round: round k's couplings are aligned (the align stage's settings) before
    # round k + 1's flow trains on them, not only before distillation
    align_rounds: bool = False


@dataclass
class AlignStageConfig:
    eps: float = 0.1  # the reference code's threshold
    variant: str = "same_window"  # same_window | matching_obs
    tol: float = 1e-3  # matching_obs: max-abs difference of the base encoder's features


@dataclass
class DistillStageConfig:
    align: bool = True  # False: distil on the unaligned couplings (the plain reflow baseline)
    train_overrides: list[str] = field(default_factory=list)


@dataclass
class PipelineConfig:
    device: str | None = None  # auto | cpu | cuda | cuda:N | mps for every stage (not cached on)
    threads: int | None = None  # torch's CPU threads for every command (not cached on)
    train: list[str] = field(default_factory=list)  # key=value overrides of TrainConfig
    train_config: str | None = None  # a YAML TrainConfig file
    reflow: ReflowStageConfig = field(default_factory=ReflowStageConfig)
    align: AlignStageConfig = field(default_factory=AlignStageConfig)
    distill: DistillStageConfig = field(default_factory=DistillStageConfig)


def load_pipeline(workspace: Path, path: Path | None = None) -> PipelineConfig:
    path = path or workspace / PIPELINE_FILE
    data = load_yaml(path) if path.exists() else {}
    cfg = from_dict(PipelineConfig, data, source=str(path))
    if cfg.train_config and not Path(cfg.train_config).is_absolute():
        beside = path.parent / cfg.train_config  # a preset names the train config shipped beside it
        if beside.exists():
            cfg.train_config = str(beside.resolve())
    return cfg


def save_pipeline(workspace: Path, cfg: PipelineConfig) -> None:
    atomic.write_text(workspace / PIPELINE_FILE, yaml.safe_dump(asdict(cfg), sort_keys=False))


def base_train_config(workspace: Path, cfg: PipelineConfig) -> TrainConfig:
    data = load_yaml(cfg.train_config) if cfg.train_config else {}
    return from_dict(TrainConfig, apply_overrides(data, cfg.train), source=str(workspace / PIPELINE_FILE))


# Reflow and distillation keep the base policy's observation encoder and train on its features,
# as the reference does; `training.freeze_encoder=false` in a stage's train_overrides fine-tunes it.
COUPLING_STAGE_DEFAULTS = ["training.freeze_encoder=true"]
# The frozen encoder's features of the training windows, computed once and read by every later
# stage with the same encoder (sefa_model/features.py): WORKSPACE/features/<key>/.
FEATURES_DIR = "features"


def _derived(base: TrainConfig, overrides: list[str], **flow) -> TrainConfig:
    # a derived stage sets its own length: the base flow's schedule length does not carry over
    data = config_to_dict(base)
    data["training"]["lr_decay_steps"] = None
    data = apply_overrides(data, COUPLING_STAGE_DEFAULTS + list(overrides))
    data["flow"] = {**data["flow"], **flow}
    return from_dict(TrainConfig, data)


def reflowed_flow_config(base: TrainConfig, overrides: list[str]) -> TrainConfig:
    """A reflowed flow (round >= 2): the base config, encoder frozen, t ~ U[t_eps, 1]."""
    return _derived(base, overrides)


def student_config(base: TrainConfig, overrides: list[str]) -> TrainConfig:
    """The one-step student: encoder frozen, trained at t = 0 only and sampled by one Euler step
    from there (the checkpoint records both, so nothing else needs to know)."""
    return _derived(base, overrides, solver="euler", steps=1, t_eps=0.0, t_train="start")


def _train_into(tmp: Path, cfg: TrainConfig, store: Path, log, on_step, **kwargs) -> dict:
    from sefa_model.training import Callbacks, train

    # a build folder kept after an interruption holds the checkpoint to continue from
    resume = (tmp / "checkpoints" / "latest" / "config.json").exists()
    result = train(cfg, tmp, store, callbacks=Callbacks(log=log, on_step=on_step), resume=resume,
                   **kwargs)
    return {"steps": result.steps, "train_loss": result.train_loss, "val": result.val,
            "device": cfg.training.device}


def stage_device(cfg: PipelineConfig, base: TrainConfig, device: str | None = None) -> str:
    from sefa_model.distributed import check_device_name

    return check_device_name(device or cfg.device or base.training.device or "auto",
                             key="--device" if device else "device")


def _on(cfg: TrainConfig, device: str) -> TrainConfig:
    cfg.training.device = device
    return cfg


def stages(workspace: Path, cfg: PipelineConfig, log: Callable[[str], None] = print,
           on_step: Callable[[int, int, float], None] = lambda *a: None,
           device: str | None = None) -> list[Stage]:
    """The ordered stage list of a workspace (train, reflow iterations, align, distill)."""
    store = (workspace / STORE).resolve()
    base = base_train_config(workspace, cfg)
    dev = stage_device(cfg, base, device)
    base = _on(base, dev)
    out: list[Stage] = [Stage("train", "train", {"train": cache_key_dict(base)}, [str(store)],
                              lambda tmp: _train_into(tmp, base, store, log, on_step), parallel=True)]
    r = cfg.reflow
    coupling_cfg = {k: getattr(r, k) for k in ("samples_per_window", "solver", "rtol", "atol",
                                               "batch_windows", "max_windows", "seed")}
    source = "train"
    for it in range(1, r.iters + 1):
        artifact = f"reflow/iter_{it}"
        if it == 1:
            model_cfg = None
        else:
            model_cfg = _on(reflowed_flow_config(base, r.train_overrides), dev)
        align_input = cfg.align if r.align_rounds and it > 1 else None
        stage_cfg = {"couplings": coupling_cfg, "iteration": it,
                     "reflowed_flow": cache_key_dict(model_cfg) if model_cfg else None}
        if align_input is not None:  # only then: older workspaces keep their cache keys
            stage_cfg["aligned_input"] = asdict(align_input)
        out.append(Stage(f"reflow iter {it}", artifact, stage_cfg, [str(store), source],
                         _reflow_run(workspace, store, source, artifact, model_cfg,
                                     {**coupling_cfg, "iteration": it}, dev, log, on_step,
                                     align_input),
                         parallel=True))
        source = artifact
    last_reflow = source
    a = cfg.align
    out.append(Stage("align", "align", asdict(a), [str(store), last_reflow],
                     _align_run(workspace, store, last_reflow, a, dev)))
    d = cfg.distill
    distill_cfg = _on(student_config(base, d.train_overrides), dev)
    inputs = [str(store), last_reflow] + (["align"] if d.align else [])
    out.append(Stage("distill", "distill", {"align": d.align, "train": cache_key_dict(distill_cfg)},
                     inputs, _distill_run(workspace, store, last_reflow, d.align, distill_cfg, log, on_step),
                     parallel=True))
    return out


def _policy_dir(workspace: Path, artifact: str) -> Path:
    """The checkpoint a reflow artifact's couplings came from."""
    if artifact == "train":
        return workspace / "train" / "checkpoints" / "latest"
    flow = workspace / artifact / "flow" / "checkpoints" / "latest"
    return flow if flow.exists() else _policy_dir(workspace, _previous(artifact))


def _previous(artifact: str) -> str:
    it = int(artifact.rsplit("_", 1)[1])
    return "train" if it == 1 else f"reflow/iter_{it - 1}"


def _reflow_run(workspace, store, source, artifact, model_cfg, coupling_cfg, device, log, on_step,
                align_input: AlignStageConfig | None = None):
    def run(tmp: Path) -> dict:
        from sefa_model.couplings import PairSource
        from sefa_model.distributed import context
        from sefa_model.policy import Policy
        from sefa_model.reflow import CouplingConfig, generate_couplings

        summary = {}
        checkpoint = _policy_dir(workspace, source)
        label = str(checkpoint.relative_to(workspace))
        if model_cfg is not None:  # train a reflowed flow on the previous couplings, uniform t
            couplings = workspace / source / "couplings.zarr"
            trained_on = PairSource.couplings(couplings, "reflow")
            if align_input is not None:
                ctx = context()
                aligned = tmp / "trained_on_aligned.zarr"
                if ctx.is_main:
                    summary["aligned_input"] = _aligned(workspace, store, couplings, aligned,
                                                        align_input, device)
                    log(f"aligned {source}'s couplings before training on them: replaced "
                        f"{summary['aligned_input']['fraction_replaced']:.1%} (eps {align_input.eps:g})")
                ctx.barrier()
                trained_on = PairSource.aligned(aligned, "reflow")
            log(f"training a reflowed flow on {source}'s couplings")
            summary["flow"] = _train_into(
                tmp / "flow", model_cfg, store, log, on_step, couplings=trained_on,
                init_from=checkpoint, features_cache=workspace / FEATURES_DIR)
            checkpoint = tmp / "flow" / "checkpoints" / "latest"
            label = f"{artifact}/flow/checkpoints/latest"  # where it lives once the stage is done
        policy = Policy.load(checkpoint, device=device)
        log(f"generating couplings from {label} on {policy.device}")
        summary["couplings"] = generate_couplings(policy, store, tmp / "couplings.zarr",
                                                  CouplingConfig(**coupling_cfg), source=label,
                                                  features_cache=workspace / FEATURES_DIR)
        return summary
    return run


def _aligned(workspace: Path, store: Path, couplings: Path, out: Path, a: AlignStageConfig,
             device: str) -> dict:
    """Align `couplings` to the expert chunks of the store's training windows into `out`."""
    from sefa_model.alignment import align_to_expert

    return align_to_expert(_policy_dir(workspace, "train"), store, couplings, out, a.eps,
                           variant=a.variant, tol=a.tol, device=device,
                           features_cache=workspace / FEATURES_DIR)


def _align_run(workspace, store, reflow, a: AlignStageConfig, device):
    def run(tmp: Path) -> dict:
        return _aligned(workspace, store, workspace / reflow / "couplings.zarr", tmp / "aligned.zarr",
                        a, device)
    return run


def _distill_run(workspace, store, reflow, use_align, cfg, log, on_step):
    def run(tmp: Path) -> dict:
        from sefa_model.couplings import PairSource

        init = _policy_dir(workspace, reflow)
        couplings = (PairSource.aligned(workspace / "align" / "aligned.zarr", "sefa_one_step")
                     if use_align else
                     PairSource.couplings(workspace / reflow / "couplings.zarr", "reflow_one_step"))
        return _train_into(tmp, cfg, store, log, on_step, init_from=init, couplings=couplings,
                           features_cache=workspace / FEATURES_DIR)
    return run


def run_stages(workspace: Path, cfg: PipelineConfig, names: list[str] | None = None,
               force: set[str] | None = None, log=print, on_step=lambda *a: None,
               device: str | None = None) -> list:
    """Run the named stages (default: all) in order; the runner skips cached ones."""
    all_stages = stages(workspace, cfg, log, on_step, device)
    chosen = [s for s in all_stages if names is None or s.name.split(" ")[0] in names]
    # `--force` on `sefa reflow` names every reflow round ("reflow iter 1", "reflow iter 2")
    forced = {s.name for s in chosen if s.name in (force or ()) or s.name.split(" ")[0] in (force or ())}
    return run_pipeline(Workspace(workspace), chosen, force=forced, log=log)
