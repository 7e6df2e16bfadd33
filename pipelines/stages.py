"""The SeFA stages of a workspace, as cached runner stages.

    WORKSPACE/dataset.zarr        sefa ingest (cached by each input's sha256)
    WORKSPACE/train/              the base rectified flow                 sefa train
    WORKSPACE/reflow/iter_1/      couplings of the base flow              sefa reflow --iters N
    WORKSPACE/reflow/iter_k/      a reflowed flow trained on iter_{k-1}'s couplings, and its couplings
    WORKSPACE/align/              the selectively aligned couplings       sefa align --eps E
    WORKSPACE/distill/            the one-step policy                     sefa distill [--no-align]

Each stage's config is its fully resolved settings; its inputs are the store (a file
fingerprint) and its upstream artifacts (manifest hashes), so changing `--eps` reruns align and
distill only. The stage settings of a workspace live in WORKSPACE/sefa.yaml (written by `sefa
run PIPELINE` into a workspace without one, and by `--save`, which keeps the replaced file as
sefa.yaml.bak) so that bare commands chain.

Where a stage runs (`device`, loader workers, the number of torchrun processes) is not part of
its cache key: a workspace trained on a laptop's CPU is reused, not retrained, on a GPU server.
The device is `--device` of the command, else `device:` in sefa.yaml, else the train config's
`training.device`, else auto.
"""

from __future__ import annotations

import copy
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Collection

import yaml

from sefa_pipelines.runner import Extension, Stage, Workspace, run_pipeline
from sefa_data import atomic
from sefa_data.config_io import apply_overrides, from_dict, load_yaml
from sefa_data.errors import ConfigError, SefaInputError
from sefa_data.ranges import NONNEGATIVE, POSITIVE, SEED, UNIT, count, knob
from sefa_model import methods
from sefa_model.policy.execution import ExecutionSettings
from sefa_model.config import (UNKEYED_TRAINING, TrainConfig, cache_key_dict, config_to_dict,
                               lr_schedule_length)
from sefa_model.methods import reflowed_flow_config, student_config  # noqa: F401 (stage recipes)

PIPELINE_FILE = "sefa.yaml"
STORE = "dataset.zarr"


@dataclass
class ReflowStageConfig:
    iters: int = knob(1, count(1, 100))
    samples_per_window: int = knob(10, count(1, 10_000))
    solver: str = "rk45"
    rtol: float = knob(1e-5, POSITIVE)
    atol: float = knob(1e-5, POSITIVE)
    batch_windows: int = knob(256, count(1, 1_000_000))
    max_windows: int | None = knob(None, count(1))  # more than the store has: every window
    seed: int = knob(0, SEED)
    train_overrides: list[str] = field(default_factory=list)  # for the reflowed flows (iter >= 2)
    # the reflowed flows' training steps (`sefa reflow --train-steps`); None: train_overrides', else
    # the base flow's training.max_steps
    train_steps: int | None = knob(None, count(1, 100_000_000))
    # align every round: round k's couplings are aligned (the align stage's settings) before
    # round k + 1's flow trains on them, not only before distillation
    align_rounds: bool = False

    def validate(self) -> None:
        from sefa_model.config import SOLVERS  # not sefa_model.flow.solvers: that imports torch

        if self.solver not in SOLVERS:
            raise ConfigError(f"unknown solver '{self.solver}' (valid: {', '.join(SOLVERS)})",
                              key="solver")


@dataclass
class AlignStageConfig:
    eps: float = knob(0.1, NONNEGATIVE)  # the reference code's threshold
    variant: str = "same_window"  # same_window | matching_obs
    tol: float = knob(1e-3, NONNEGATIVE)  # matching_obs: max-abs difference of the base encoder's features
    # set: eps is chosen from the data, the smallest that replaces this fraction of the couplings
    # (the nearest ones; `sefa align --eps auto` sets alignment.AUTO_FRACTION), and `eps` is unused
    replace_fraction: float | None = knob(None, UNIT)

    def validate(self) -> None:
        if self.variant not in ALIGN_VARIANTS:
            raise ConfigError(f"unknown variant '{self.variant}' (valid: {', '.join(ALIGN_VARIANTS)})",
                              key="variant")

    def cache_key(self) -> dict:
        """The settings the stage is cached on; replace_fraction only when set, so that the
        workspaces aligned before it existed stay cached."""
        key = asdict(self)
        if key["replace_fraction"] is None:
            del key["replace_fraction"]
        return key

    def describe(self) -> str:
        return (f"eps {self.eps:g}" if self.replace_fraction is None else
                f"eps chosen to replace the nearest {self.replace_fraction:.0%}")


ALIGN_VARIANTS = ("same_window", "matching_obs")


@dataclass
class DistillStageConfig:
    # how the student is trained (sefa_model/methods: `sefa distill --method NAME`); a method
    # that distils the base flow on fresh noise (mean_flow, shortcut) reads no couplings
    method: str = methods.STUDENTS_DEFAULT
    align: bool = True  # False: distil on the unaligned couplings (the plain reflow baseline)
    # Euler steps the student samples with: 1 is the one-step policy; k > 1 trains the velocity
    # at the k times k Euler steps visit (flow.t_train: grid), k network evaluations per chunk
    steps: int = knob(1, count(1, 64))
    train_overrides: list[str] = field(default_factory=list)
    # the student's training steps (`sefa distill --train-steps`); None: train_overrides',
    # else the base flow's training.max_steps
    train_steps: int | None = knob(None, count(1, 100_000_000))

    def validate(self) -> None:
        methods.check_student(self.method)  # unknown, or not a student: one line


@dataclass
class PipelineConfig:
    device: str | None = None  # auto | cpu | cuda | cuda:N | mps for every stage (not cached on)
    threads: int | None = knob(None, count(1, 4096))  # torch's CPU threads for every command (not cached on)
    train: list[str] = field(default_factory=list)  # key=value overrides of TrainConfig
    train_config: str | None = None  # a YAML TrainConfig file
    reflow: ReflowStageConfig = field(default_factory=ReflowStageConfig)
    align: AlignStageConfig = field(default_factory=AlignStageConfig)
    distill: DistillStageConfig = field(default_factory=DistillStageConfig)
    # how `sefa eval --env` and `sefa serve` execute chunks when no --execution is given (None:
    # the one chosen for each policy, else receding; sefa_model/policy/execution.py); no stage
    # reads it
    execution: ExecutionSettings | None = None


def load_pipeline(workspace: Path, path: Path | None = None) -> PipelineConfig:
    """A named file must exist; only the workspace's own sefa.yaml may be absent (the defaults)."""
    if path is None:
        path = workspace / PIPELINE_FILE
        data = load_yaml(path) if path.exists() else {}
    else:
        data = load_yaml(path)
    return pipeline_from_data(data, path, str(path))


def pipeline_from_data(data: dict, path: Path, source: str | None) -> PipelineConfig:
    """The typed settings of a pipeline file's contents, `path` being where the file is
    (`source`: the file an error names, if any)."""
    cfg = from_dict(PipelineConfig, data, source=source)
    if cfg.train_config and not Path(cfg.train_config).is_absolute():
        beside = path.parent / cfg.train_config  # a preset names the train config shipped beside it
        if beside.exists():
            cfg.train_config = str(beside.resolve())
    return cfg


def save_pipeline(workspace: Path, cfg: PipelineConfig) -> None:
    """Write sefa.yaml; settings it had before are kept as sefa.yaml.bak (a tuned config is
    never lost to one command)."""
    write_pipeline_text(workspace, yaml.safe_dump(asdict(cfg), sort_keys=False))


def write_pipeline_text(workspace: Path, text: str) -> None:
    """sefa.yaml's new text, written atomically; the old text kept as sefa.yaml.bak. A
    sefa.yaml that is a symlink (to a config kept in a repository, say) stays one: the file it
    points to is replaced."""
    path = workspace / PIPELINE_FILE
    if path.exists():
        old = path.read_bytes()
        if old == text.encode():
            return
        atomic.write_bytes(path.with_name(PIPELINE_FILE + ".bak"), old)
    target = Path(os.path.realpath(path)) if path.is_symlink() else path
    atomic.write_text(target, text)


def base_train_config(workspace: Path, cfg: PipelineConfig) -> TrainConfig:
    data = load_yaml(cfg.train_config) if cfg.train_config else {}
    source = str(workspace / PIPELINE_FILE)
    base = from_dict(TrainConfig, apply_overrides(data, cfg.train), source=source)
    if base.method is not None or base.method_config:  # else the base flow: nothing to load
        methods.base_method(base)  # named as given: `method=...` on a command line or in train:
    return _pin_observation_set(base, workspace / STORE)


def _pin_observation_set(cfg: TrainConfig, store: Path) -> TrainConfig:
    """A config that names observation keys without `obs_keys` (every preset made before issue
    25) reads as "every store key" now and as "the named keys" before. Where the store shows the
    two are the same set in the same order, it is written out as `obs_keys`: the config then
    keeps its old cache key, and a workspace made before the change is not retrained for a
    change of words."""
    meta = cfg.shape_meta
    if meta.obs_keys is not None or not meta.obs or not store.exists():
        return cfg
    from sefa_data.store.zarr_store import EpisodeStore
    from sefa_model.policy.model import observation_keys

    try:
        used, _ = observation_keys(cfg, EpisodeStore.open(store))
    except (SefaInputError, ConfigError, OSError, KeyError):  # the stages report the store
        return cfg
    if used == list(meta.obs):
        meta.obs_keys = list(meta.obs)
    return cfg


# Reflow and distillation keep the base policy's observation encoder and train on its features,
# as the reference does (sefa_model/methods/base.py: DERIVED_STAGE_DEFAULTS);
# `training.freeze_encoder=false` in a stage's train_overrides fine-tunes it.
# The frozen encoder's features of the training windows, computed once and read by every later
# stage with the same encoder (sefa_model/data/features.py): WORKSPACE/features/<key>/.
FEATURES_DIR = "features"


# --- the stage graph -----------------------------------------------------------------------------
# The one place that knows which stages a workspace has, what each reads and where its files are;
# the stage list, the commands' upstream stages, `sefa status` and `sefa eval`'s defaults all
# derive from it.

CHECKPOINT = "checkpoints/latest"  # a training run's current checkpoint, inside its run folder
COUPLINGS = "couplings.zarr"  # a reflow round's couplings, inside its artifact
# a reflow round's finished blocks while it runs, in its build folder (kept by an interrupt,
# reused by the next run, removed once COUPLINGS is written: sefa_model/sefa/reflow.py)
COUPLING_BLOCKS = "couplings.blocks"
ALIGNED = "aligned.zarr"  # the aligned couplings, inside the align artifact
FLOW = "flow"  # a reflowed flow's run folder (rounds >= 2), inside its round's artifact


@dataclass(frozen=True)
class StageSpec:
    """One node of the graph: the command that builds it, its artifact, what it reads."""

    command: str  # train | reflow | align | distill: `sefa COMMAND` builds it
    artifact: str  # its folder in the workspace
    inputs: tuple[str, ...] = ()  # upstream artifacts (every stage also reads the store)
    round: int | None = None  # reflow rounds: 1, 2, ...
    policy: str | None = None  # the policy it trains: its run folder in the artifact ("": the artifact)

    @property
    def name(self) -> str:
        return self.command if self.round is None else f"{self.command} iter {self.round}"

    @property
    def policy_dir(self) -> str | None:
        """The policy it trains, as the workspace names it (train, reflow/iter_2/flow)."""
        if self.policy is None:
            return None
        return f"{self.artifact}/{self.policy}" if self.policy else self.artifact


def stage_graph(cfg: PipelineConfig) -> list[StageSpec]:
    """The stages of a workspace with these settings, in the order they run."""
    graph = [StageSpec("train", "train", policy="")]
    for it in range(1, cfg.reflow.iters + 1):
        # round 1 samples the base flow; each later round first trains a flow on the last couplings
        graph.append(StageSpec("reflow", f"reflow/iter_{it}", (graph[-1].artifact,), round=it,
                               policy=None if it == 1 else FLOW))
    last_reflow = graph[-1].artifact
    graph.append(StageSpec("align", "align", (last_reflow,)))
    inputs = (("train",) if distils_base_flow(cfg) else
              (last_reflow, "align") if cfg.distill.align else (last_reflow,))
    graph.append(StageSpec("distill", "distill", inputs, policy=""))
    return graph


def spec_of(graph: list[StageSpec], artifact: str) -> StageSpec:
    return next(s for s in graph if s.artifact == artifact)


def command_of(stage: Stage) -> str:
    """The command that builds a stage of the list (its name's first word: "reflow iter 2")."""
    return stage.name.split(" ")[0]


def needed(graph: list[StageSpec], command: str) -> list[StageSpec]:
    """The stages `sefa COMMAND` runs: the command's own and every one they read, in order."""
    wanted = {s.artifact for s in graph if s.command == command}
    for spec in reversed(graph):
        if spec.artifact in wanted:
            wanted.update(spec.inputs)
    return [s for s in graph if s.artifact in wanted]


def coupling_source(graph: list[StageSpec], artifact: str) -> str:
    """The policy whose samples a reflow round's couplings are (its own flow, else round 1's
    source, the base flow), as the workspace names it."""
    spec = spec_of(graph, artifact)
    while spec.policy_dir is None:
        spec = spec_of(graph, spec.inputs[0])
    return spec.policy_dir


def checkpoint_dir(workspace: Path, policy_dir: str) -> Path:
    return workspace / policy_dir / CHECKPOINT


def eval_defaults(graph: list[StageSpec], workspace: Path) -> list[Path]:
    """What `sefa eval` evaluates without arguments: the base flow, the last reflowed flow that
    exists and the one-step policy, each where it has a checkpoint."""
    flows = [s.policy_dir for s in graph if s.command == "reflow" and s.policy_dir]
    last_flow = next((f for f in reversed(flows) if checkpoint_dir(workspace, f).exists()), None)
    chosen = [spec_of(graph, "train").policy_dir, last_flow, spec_of(graph, "distill").policy_dir]
    return [workspace / p for p in chosen if p and checkpoint_dir(workspace, p).exists()]


def distils_base_flow(cfg: PipelineConfig) -> bool:
    """Whether the student reads no couplings: its method distils the base flow on fresh noise."""
    return methods.distils_base_flow(cfg.distill.method)


def steps_source(cfg: PipelineConfig, command: str) -> str:
    """Where a training stage's step count comes from, in words (announced before it runs)."""
    if command == "train":
        named = any(o.startswith("training.max_steps=") for o in cfg.train)
        return ("training.max_steps in the train settings" if named else
                f"training.max_steps of {'the train config file' if cfg.train_config else 'the defaults'}")
    section = cfg.reflow if command == "reflow" else cfg.distill
    if section.train_steps is not None:
        return f"{command}.train_steps (`sefa {command} --train-steps`)"
    if any(o.startswith("training.max_steps=") for o in section.train_overrides):
        return f"{command}.train_overrides"
    return (f"inherited from the base flow's training.max_steps; `sefa {command} --train-steps N` "
            f"sets it")


def unkeyed(section: str) -> tuple[str, ...]:
    """A train config's unkeyed keys as they sit in a stage config, under `section`."""
    return tuple(f"{section}.training.{k}" for k in UNKEYED_TRAINING)


_LENGTH = ("max_steps", "lr_decay_steps")


def longer_run(section: str, resume: bool):
    """A stage's `extends` (pipelines/runner.py): a finished run of the same settings but fewer
    steps is continued to the new length, from its last checkpoint, when the learning-rate
    schedule over the steps it did is the one this run has (then the weights are those of a
    run from step 0). Otherwise it is continued only when asked (`--resume`), as Diffusion
    Policy's resume does: the schedule then goes on with the new length from that step."""
    def extends(old: dict, new: dict, run: str) -> Extension | None:
        o, n = old.get(section), new.get(section)
        if not (isinstance(o, dict) and isinstance(n, dict)):
            return None
        ot, nt = o.get("training") or {}, n.get("training") or {}
        if not isinstance(ot.get("max_steps"), int) or nt["max_steps"] <= ot["max_steps"]:
            return None

        def rest(cfg: dict, t: dict) -> dict:
            return {**cfg, section: {**cfg[section], "training": {
                k: v for k, v in t.items() if k not in _LENGTH}}}
        if rest(old, ot) != rest(new, nt):
            return None
        done, todo = ot["max_steps"], nt["max_steps"]
        was, now = lr_schedule_length(ot), lr_schedule_length(nt)
        if was == now:
            return Extension(True, True, f"continuing {run} from step {done} to {todo}: the same "
                             f"settings and learning-rate schedule (over {now} steps), so the "
                             f"weights are those of a run from step 0")
        differs = (f"its learning rate decayed over {was} steps, this run's over {now}")
        if resume:
            return Extension(True, False, f"continuing {run} from step {done} to {todo} "
                             f"(--resume): {differs}, so the schedule goes on from step {done} "
                             f"as if it had always been {now} steps long; a run from step 0 "
                             f"would differ (recorded as continued_from in its manifest)")
        return Extension(False, False, f"starting from step 0: {run} has {done} of these steps "
                         f"done, but {differs}. `--resume` continues it anyway; with "
                         f"training.lr_decay_steps at the longest length you will ask for, "
                         f"a longer run continues exactly")
    return extends


def observation_notes(cfg: TrainConfig, store: Path) -> tuple[list[str], dict[str, dict]]:
    """The lines a training starts with (its observation keys, shapes and slices, and the
    store's keys shape_meta.obs_keys leaves out) and the record its manifest keeps."""
    import copy

    from sefa_data.store.zarr_store import EpisodeStore
    from sefa_model.policy.model import (describe_observation, observation_keys,
                                        observation_record, resolve_shapes)

    opened = EpisodeStore.open(store)
    _, left_out = observation_keys(cfg, opened)
    record = observation_record(resolve_shapes(copy.deepcopy(cfg), opened))
    notes = [f"observations ({len(record)}): "
             + ", ".join(describe_observation(k, r) for k, r in record.items())]
    if left_out:
        notes.append(f"not observed: {', '.join(left_out)} (left out by shape_meta.obs_keys)")
    return notes, record


@dataclass(frozen=True)
class StageContext:
    """What every stage's run reads besides its own settings: the workspace, its store and
    stage graph, the device the stages run on, and where they report."""

    workspace: Path
    store: Path
    graph: list[StageSpec]
    device: str
    log: Callable[[str], None] = print
    on_step: Callable[[int, int, float], None] = lambda *a: None

    @property
    def features(self) -> Path:
        return self.workspace / FEATURES_DIR

    def checkpoint(self, policy_dir: str) -> Path:
        return checkpoint_dir(self.workspace, policy_dir)

    def source_checkpoint(self, artifact: str) -> Path:
        """The checkpoint of the policy whose samples `artifact`'s couplings are."""
        return self.checkpoint(coupling_source(self.graph, artifact))


def _train_into(ctx: StageContext, tmp: Path, cfg: TrainConfig, **kwargs) -> dict:
    from sefa_model.train.loop import Callbacks, train

    store, log = ctx.store, ctx.log
    notes, observations = observation_notes(cfg, store)
    for note in notes:
        log(note)

    # a build folder kept after an interruption holds the checkpoint to continue from
    # (or the copy of a shorter finished run that the runner continues: its length is this cfg's)
    resume = (tmp / CHECKPOINT / "config.json").exists()
    result = train(cfg, tmp, store, callbacks=Callbacks(log=log, on_step=ctx.on_step),
                   resume=resume, extend=resume, **kwargs)
    return {"steps": result.steps, "train_loss": result.train_loss, "val": result.val,
            "device": cfg.training.device, "observations": observations}


def stage_device(cfg: PipelineConfig, base: TrainConfig, device: str | None = None) -> str:
    from sefa_model.distributed import check_device_name

    return check_device_name(device or cfg.device or base.training.device or "auto",
                             key="--device" if device else "device")


def check_fits(workspace: Path, cfg: PipelineConfig, commands: set[str],
               device: str | None = None, base: TrainConfig | None = None) -> None:
    """The batches of the trainings that `commands` will run, against the data they draw from
    and the memory of the device (sefa_model/train/limits.py); before any work, so a batch that
    cannot run is one line, not a killed process. Without a store the runner says it is missing.
    `base`: the workspace's base config when the caller has built it (not changed here)."""
    from sefa_model.distributed import context
    from sefa_model.train.limits import check_batch, training_windows

    store = workspace / STORE
    if not store.exists() or not commands & {"train", "reflow", "distill"}:
        return
    base = _base(workspace, cfg, base)
    dev = stage_device(cfg, base, device)
    base = _on(base, dev)
    world = context().world
    if "train" in commands:
        check_batch(base, store, world=world)
    derived = []
    if "reflow" in commands and cfg.reflow.iters >= 2:
        derived.append(("a reflowed flow", reflowed_flow_config(base, cfg.reflow.train_overrides,
                                                                cfg.reflow.train_steps)))
    if "distill" in commands:
        derived.append(("the student", student_config(base, cfg.distill.train_overrides,
                                                      cfg.distill.train_steps,
                                                      cfg.distill.steps, cfg.distill.method)))
    if derived:
        n = training_windows(base, store)
        used = min(cfg.reflow.max_windows or n, n)
        k = cfg.reflow.samples_per_window
        for who, c in derived:
            check_batch(_on(c, dev), store, draws=used * k, world=world,
                        what=f"couplings {who} trains on ({used} windows x {k} samples)")


def _base(workspace: Path, cfg: PipelineConfig, built: TrainConfig | None) -> TrainConfig:
    """The base config to change here: a copy of the caller's, else built from the files."""
    return copy.deepcopy(built) if built is not None else base_train_config(workspace, cfg)


def _on(cfg: TrainConfig, device: str) -> TrainConfig:
    cfg.training.device = device
    return cfg


def stages(workspace: Path, cfg: PipelineConfig, log: Callable[[str], None] = print,
           on_step: Callable[[int, int, float], None] = lambda *a: None,
           device: str | None = None, resume: bool = False,
           base: TrainConfig | None = None) -> list[Stage]:
    """The ordered stage list of a workspace: its graph's nodes with their settings and runs.
    `resume`: a training continues a shorter finished run even when its schedule differs.
    `base`: the workspace's base config when the caller has built it (not changed here)."""
    store = (workspace / STORE).resolve()
    base = _base(workspace, cfg, base)
    dev = stage_device(cfg, base, device)
    base = _on(base, dev)
    graph = stage_graph(cfg)
    ctx = StageContext(workspace, store, graph, dev, log, on_step)
    out: list[Stage] = []
    for spec in graph:
        if spec.command == "train":
            out.append(_train_stage(ctx, spec, cfg, base, resume))
        elif spec.command == "reflow":
            out.append(_reflow_stage(ctx, spec, cfg, base))
        elif spec.command == "align":
            out.append(Stage(spec.name, spec.artifact, cfg.align.cache_key(),
                             [str(store), *spec.inputs], _align_run(ctx, spec.inputs[0], cfg.align)))
        else:
            out.append(_distill_stage(ctx, spec, cfg, base, resume))
    return out


def _train_stage(ctx: StageContext, spec: StageSpec, cfg: PipelineConfig, base: TrainConfig,
                 resume: bool) -> Stage:
    return Stage(spec.name, spec.artifact, {"train": cache_key_dict(base)},
                 [str(ctx.store), *spec.inputs],
                 _announced(f"train: {base.training.max_steps} steps ({steps_source(cfg, 'train')}"
                            f"), batch {base.training.batch_size}", ctx.log,
                            lambda tmp: _train_into(ctx, tmp, base)),
                 parallel=True, unkeyed=unkeyed("train"), extends=longer_run("train", resume))


def _distill_stage(ctx: StageContext, spec: StageSpec, cfg: PipelineConfig, base: TrainConfig,
                   resume: bool) -> Stage:
    d = cfg.distill
    distill_cfg = _on(student_config(base, d.train_overrides, d.train_steps, d.steps, d.method),
                      ctx.device)
    return Stage(spec.name, spec.artifact, {"align": d.align, "train": cache_key_dict(distill_cfg)},
                 [str(ctx.store), *spec.inputs],
                 _announced(f"distill: {distill_cfg.training.max_steps} steps ("
                            f"{steps_source(cfg, 'distill')}), batch "
                            f"{distill_cfg.training.batch_size}", ctx.log,
                            _distill_run(ctx, spec.inputs[0], d.align, distill_cfg)),
                 parallel=True, unkeyed=unkeyed("train"), extends=longer_run("train", resume))


def _reflow_stage(ctx: StageContext, spec: StageSpec, cfg: PipelineConfig, base: TrainConfig
                  ) -> Stage:
    r = cfg.reflow
    coupling_cfg = {k: getattr(r, k) for k in ("samples_per_window", "solver", "rtol", "atol",
                                               "batch_windows", "max_windows", "seed")}
    it = spec.round
    model_cfg = (None if spec.policy is None else
                 _on(reflowed_flow_config(base, r.train_overrides, r.train_steps), ctx.device))
    align_input = cfg.align if r.align_rounds and it > 1 else None
    stage_cfg = {"couplings": coupling_cfg, "iteration": it,
                 "reflowed_flow": cache_key_dict(model_cfg) if model_cfg else None}
    if align_input is not None:  # only then: older workspaces keep their cache keys
        stage_cfg["aligned_input"] = align_input.cache_key()
    return Stage(spec.name, spec.artifact, stage_cfg, [str(ctx.store), *spec.inputs],
                 _announced(lambda: _reflow_cost(ctx.store, spec, cfg, base, model_cfg), ctx.log,
                            _reflow_run(ctx, spec, model_cfg, {**coupling_cfg, "iteration": it},
                                        align_input)),
                 parallel=True, unkeyed=unkeyed("reflowed_flow"))


def _announced(line: str | Callable[[], str], log, run: Callable[[Path], dict]
               ) -> Callable[[Path], dict]:
    """A stage's run that first says what it will cost (before any work)."""
    def announced(tmp: Path) -> dict:
        from sefa_model.distributed import context

        if context().is_main:
            log(line if isinstance(line, str) else line())
        return run(tmp)
    return announced


def _reflow_cost(store: Path, spec: StageSpec, cfg: PipelineConfig, base: TrainConfig,
                 model_cfg: TrainConfig | None) -> str:
    """`reflow iter 2: trains a reflowed flow, 1000 steps (inherited ...); then 21697 windows x
    K=10 = 216970 couplings with rk45`. The ETA comes with the progress, from the first block."""
    from sefa_model.train.limits import training_windows

    r = cfg.reflow
    what = f"{spec.name}: "
    if model_cfg is not None:
        what += (f"trains a reflowed flow, {model_cfg.training.max_steps} steps "
                 f"({steps_source(cfg, 'reflow')}); then ")
    try:
        n = training_windows(base, store)
        used = min(r.max_windows or n, n)
        windows = f"{used} windows" + (f" of {n}" if used < n else "")
        couplings = f" = {used * r.samples_per_window} couplings"
    except (SefaInputError, OSError):  # the stage itself reports an unreadable store
        windows, couplings = "every training window", ""
    return (f"{what}{windows} x K={r.samples_per_window}{couplings} with {r.solver}, "
            f"{r.batch_windows} windows per block")


def _reflow_run(ctx: StageContext, spec: StageSpec, model_cfg: TrainConfig | None,
                coupling_cfg: dict, align_input: AlignStageConfig | None = None):
    def run(tmp: Path) -> dict:
        from sefa_model.data.couplings import PairSource
        from sefa_model.distributed import context
        from sefa_model.policy.artifact import Policy
        from sefa_model.sefa.reflow import CouplingConfig, generate_couplings

        log, source, summary = ctx.log, spec.inputs[0], {}
        checkpoint = ctx.source_checkpoint(source)
        label = str(checkpoint.relative_to(ctx.workspace))
        if model_cfg is not None:  # train a reflowed flow on the previous couplings, uniform t
            couplings = ctx.workspace / source / COUPLINGS
            trained_on = PairSource.couplings(couplings, "reflow")
            if align_input is not None:
                dist = context()
                aligned = tmp / "trained_on_aligned.zarr"
                if dist.is_main:
                    summary["aligned_input"] = _aligned(ctx, couplings, aligned, align_input)
                    log(f"aligned {source}'s couplings before training on them: replaced "
                        f"{summary['aligned_input']['fraction_replaced']:.1%} (eps "
                        f"{summary['aligned_input']['eps']:.4g})")
                dist.barrier()
                trained_on = PairSource.aligned(aligned, "reflow")
            log(f"training a reflowed flow on {source}'s couplings")
            summary["flow"] = _train_into(ctx, tmp / FLOW, model_cfg, couplings=trained_on,
                                          init_from=checkpoint, features_cache=ctx.features)
            checkpoint = tmp / FLOW / CHECKPOINT
            label = f"{spec.policy_dir}/{CHECKPOINT}"  # where it lives once the stage is done
        policy = Policy.load(checkpoint, device=ctx.device)
        log(f"generating couplings from {label} on {policy.device}")
        summary["couplings"] = generate_couplings(policy, ctx.store, tmp / COUPLINGS,
                                                  CouplingConfig(**coupling_cfg), source=label,
                                                  features_cache=ctx.features,
                                                  blocks_dir=tmp / COUPLING_BLOCKS, log=log)
        return summary
    return run


def _aligned(ctx: StageContext, couplings: Path, out: Path, a: AlignStageConfig) -> dict:
    """Align `couplings` to the expert chunks of the store's training windows into `out`."""
    from sefa_model.sefa.alignment import align_to_expert

    return align_to_expert(ctx.checkpoint("train"), ctx.store, couplings, out, a.eps,
                           variant=a.variant, tol=a.tol, device=ctx.device,
                           features_cache=ctx.features, replace_fraction=a.replace_fraction)


def _align_run(ctx: StageContext, reflow: str, a: AlignStageConfig):
    def run(tmp: Path) -> dict:
        return _aligned(ctx, ctx.workspace / reflow / COUPLINGS, tmp / ALIGNED, a)
    return run


def _distill_run(ctx: StageContext, reflow: str, use_align: bool, cfg: TrainConfig):
    def run(tmp: Path) -> dict:
        from sefa_pipelines.report import distill_alignment_line
        from sefa_model.data.couplings import PairSource, aligned_attrs

        init, log = ctx.source_checkpoint(reflow), ctx.log
        method = methods.method_of(cfg).name
        if reflow == "train":  # a method that distils the base flow on fresh noise
            log(f"distill: {method} distils the base flow on fresh noise at every step; it "
                f"reads no couplings, so alignment does not apply")
            summary = _train_into(ctx, tmp, cfg, init_from=init, features_cache=ctx.features)
            return {**summary, "kind": "one_step", "alignment": None, "method": method}
        alignment = None
        if use_align:
            aligned = ctx.workspace / "align" / ALIGNED
            a = aligned_attrs(aligned)
            alignment = {k: a.get(k) for k in ("eps", "replace_fraction", "n", "n_replaced",
                                                "fraction_replaced")}
            log(distill_alignment_line(alignment))
            # nothing replaced: the targets are the generated chunks, so the student is plain
            # reflow and is labelled so
            kind = "sefa_one_step" if alignment["n_replaced"] else "reflow_one_step"
            couplings = PairSource.aligned(aligned, kind)
        else:
            couplings = PairSource.couplings(ctx.workspace / reflow / COUPLINGS, "reflow_one_step")
        summary = _train_into(ctx, tmp, cfg, init_from=init, couplings=couplings,
                              features_cache=ctx.features)
        return {**summary, "kind": couplings.kind, "alignment": alignment, "method": method}
    return run


def select(all_stages: list[Stage], graph: list[StageSpec], command: str | None,
           force: Collection[str] = ()) -> tuple[list[Stage], set[str]]:
    """(the stages `sefa COMMAND` runs, default all; the names of those to rerun). `force` names
    stages or commands: `--force` on `sefa reflow` names every round ("reflow iter 1", ...)."""
    wanted = None if command is None else {s.artifact for s in needed(graph, command)}
    chosen = [s for s in all_stages if wanted is None or s.artifact in wanted]
    return chosen, {s.name for s in chosen if s.name in force or command_of(s) in force}


def run_stages(workspace: Path, cfg: PipelineConfig, force: set[str] | None = None, log=print,
               on_step=lambda *a: None, device: str | None = None) -> list:
    """Run every stage in order; the runner skips cached ones."""
    chosen, forced = select(stages(workspace, cfg, log, on_step, device), stage_graph(cfg), None,
                            force or ())
    return run_pipeline(Workspace(workspace), chosen, force=forced, log=log)
