"""What a workspace command does around its stages: which settings it runs with, what it must
run first, and what it says about both.

Settings. ``sefa.yaml`` is the workspace's config; a stage command's flags (``sefa train
policy.head=mlp``, ``sefa align --eps 0.05``) are kept apart in ``.sefa/flags.yaml`` and laid
over it for this and the following commands, so that bare commands chain, and are recorded in
every run they make. They reach ``sefa.yaml`` only when asked (``--save``). Every command that
runs with such flags says so in one line.

Upstream stages. A command that needs a stage it was not asked for (``sefa reflow`` without a
trained policy) does not start it silently: it names what it would run and stops, unless given
``--yes`` (``sefa run`` runs every stage by definition).

Machine defaults. On a machine without an accelerator the base policy defaults to the small MLP
head (one line says so) unless the config names a head.
"""

from __future__ import annotations

import sys
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Callable

import yaml

from sefa_pipelines.runner import (STATE_DIR, KeptRun, Stage, Workspace, kept_run_of, pipeline_status,
                              resumable_partial,
                              run_id, run_pipeline)
from sefa_pipelines.stages import (PIPELINE_FILE, PipelineConfig, base_train_config, command_of,
                              load_pipeline, save_pipeline, select, stage_graph, stages)
from sefa_data import atomic
from sefa_data.config_io import apply_overrides, from_dict, load_yaml, to_dict
from sefa_data.errors import ConfigError, SefaInputError

FLAGS_FILE = "flags.yaml"
SECTIONS = ("reflow", "align", "distill")
Log = Callable[[str], None]


# --- settings ------------------------------------------------------------------------------------

def _flags_path(workspace: Path) -> Path:
    return workspace / STATE_DIR / FLAGS_FILE


def load_flags(workspace: Path) -> dict[str, Any]:
    path = _flags_path(workspace)
    return (load_yaml(path) or {}) if path.exists() else {}


def _write_yaml(path: Path, data: dict) -> None:
    atomic.write_text(path, yaml.safe_dump(data, sort_keys=False))


def merge_overrides(old: list[str], new: list[str]) -> list[str]:
    """key=value lists, the later value of a key replacing the earlier one in place."""
    out = {item.split("=", 1)[0]: item for item in old}
    for item in new:
        out.pop(item.split("=", 1)[0], None)
        out[item.split("=", 1)[0]] = item
    return list(out.values())


def merge_flags(old: dict[str, Any], new: dict[str, Any]) -> dict[str, Any]:
    out = {k: (dict(v) if isinstance(v, dict) else list(v) if isinstance(v, list) else v)
           for k, v in old.items()}
    for key, value in new.items():
        if key == "train":
            out["train"] = merge_overrides(out.get("train", []), value)
        elif isinstance(value, dict):
            out[key] = {**out.get(key, {}), **value}
        else:
            out[key] = value
    return {k: v for k, v in out.items() if v not in ({}, [], None)}


def apply_flags(pipe: PipelineConfig, flags: dict[str, Any], source: str) -> PipelineConfig:
    data = asdict(pipe)
    for key, value in flags.items():
        if key == "train":
            data["train"] = merge_overrides(data["train"], value)
        elif isinstance(value, dict):
            data[key] = {**data[key], **value}
        else:
            data[key] = value
    return from_dict(PipelineConfig, data, source=source)


def describe_flags(flags: dict[str, Any]) -> str:
    parts = []
    for key, value in flags.items():
        if key == "train":
            parts.append("train " + " ".join(value))
        elif isinstance(value, dict):
            parts.append(f"{key} " + " ".join(f"{k}={v}" for k, v in value.items()))
        else:
            parts.append(f"{key}={value}")
    return "; ".join(parts)


def settings(workspace: Path, new_flags: dict[str, Any] | None = None, save: bool = False,
             write: bool = True) -> tuple[PipelineConfig, dict[str, Any], list[str]]:
    """(the settings a command runs with, the command-line flags in them, lines to print).

    `new_flags` are this command's; with `save` they and the earlier ones go into sefa.yaml.
    `write=False` (status, config show, non-main ranks) changes no file."""
    planned = plan_settings(workspace, new_flags, save)
    if write:
        planned.keep()
    return planned.pipe, planned.flags, planned.notes


# The command-line options that set a stage's settings, by (section, key): a bad value is
# reported under the name the user typed.
OPTION_NAMES = {("reflow", "iters"): "--iters", ("reflow", "samples_per_window"): "--samples",
                ("reflow", "max_windows"): "--max-windows", ("align", "eps"): "--eps",
                ("reflow", "train_steps"): "--train-steps",
                ("reflow", "batch_windows"): "--block-windows", ("distill", "train_steps"): "--train-steps",
                ("distill", "steps"): "--steps", ("align", "replace_fraction"): "--replace-fraction",
                ("distill", "method"): "--method"}


@dataclass
class Planned:
    """A command's settings, checked, and what it will keep of them (`keep`: flags.yaml, or
    sefa.yaml with --save). Nothing is written until `keep` runs, which a command does under the
    workspace lock once every check has passed: a refused command leaves the workspace as it was."""

    pipe: PipelineConfig
    flags: dict[str, Any]
    notes: list[str]
    keep: Callable[[], None] = lambda: None


def check_new_flags(workspace: Path, current: PipelineConfig, new_flags: dict[str, Any]) -> None:
    """This command's own values, each checked under the name it was given (`--eps`,
    `training.max_steps`), before they are merged with the workspace's."""
    from sefa_data.ranges import range_of

    for section, values in new_flags.items():
        if section not in SECTIONS or not isinstance(values, dict):
            continue
        cls = type(getattr(current, section))
        for key, value in values.items():
            valid = range_of(cls, key)
            if valid is not None:
                valid.check(value, OPTION_NAMES.get((section, key), f"{section}.{key}"))
        try:  # the section's own checks (`distill.method` a student), on the command line's values
            from_dict(cls, {**asdict(getattr(current, section)), **values})
        except ConfigError as e:  # named as typed; no file: flags.yaml does not hold them yet
            name = e.key.split(".", 1)[0].split("[", 1)[0] if e.key else None
            raise ConfigError(e.what, key=OPTION_NAMES.get((section, name), f"{section}.{e.key}")
                              if name in values else e.key) from None
    if new_flags.get("train") or new_flags.get("train_config"):
        from sefa_model.config import TrainConfig

        if new_flags.get("train_config"):
            current = from_dict(PipelineConfig, {**asdict(current),
                                                 "train_config": new_flags["train_config"]})
        data = to_dict(base_train_config(workspace, current))
        # no file in the error: the command line is where these were written
        from_dict(TrainConfig, apply_overrides(data, new_flags.get("train", [])))


def plan_settings(workspace: Path, new_flags: dict[str, Any] | None = None,
                  save: bool = False) -> Planned:
    new_flags = new_flags or {}
    base = load_pipeline(workspace)
    old = load_flags(workspace)
    if new_flags:
        check_new_flags(workspace, apply_flags(base, old, str(_flags_path(workspace))), new_flags)
    flags = merge_flags(old, new_flags)
    notes = []
    keep: Callable[[], None] = lambda: None
    if save and flags:
        base = apply_flags(base, flags, str(_flags_path(workspace)))
        saved = base

        def keep() -> None:
            save_pipeline(workspace, saved)
            _flags_path(workspace).unlink(missing_ok=True)
        notes.append(f"saved to {PIPELINE_FILE}: {describe_flags(flags)}")
        flags = {}
    elif new_flags:
        kept = flags

        def keep() -> None:
            _write_yaml(_flags_path(workspace), kept)
    result = apply_flags(base, flags, str(_flags_path(workspace)))
    if (new_flags.get("reflow") or {}).get("train_steps") is not None and result.reflow.iters < 2:
        notes.append("reflow --train-steps sets the training of the reflowed flows (rounds 2 and on); "
                     "with reflow.iters 1 no flow is trained (--iters 2 adds one)")
    if flags and new_flags:
        notes.append(f"command-line settings on top of {PIPELINE_FILE} (recorded in each run; "
                     f"kept for the next commands: --save writes them to {PIPELINE_FILE}, "
                     f"`sefa config reset` drops them): {describe_flags(flags)}")
    elif flags:
        notes.append(earlier_flags_note(flags))
    return Planned(result, flags, notes, keep)


def earlier_flags_note(flags: dict[str, Any]) -> str:
    """A command without settings of its own that runs with settings an earlier command line
    gave (`sefa train training.max_steps=20`, then `sefa train`): said first and again last,
    with how to drop them, since a cached answer would otherwise hide them."""
    return (f"note: earlier command-line settings still apply on top of {PIPELINE_FILE}: "
            f"{describe_flags(flags)} (`sefa config reset` drops them, --save writes them to "
            f"{PIPELINE_FILE})")


def reset_flags(workspace: Path) -> str:
    """`sefa config reset`: drop the command-line settings kept on top of sefa.yaml (under the
    workspace lock, as a command that keeps them writes them). Runs made with them are kept.
    Returns the line to print."""
    flags = load_flags(workspace)
    if not flags:
        return f"no command-line settings are kept: {PIPELINE_FILE} alone applies"
    with Workspace(workspace).lock():
        drop_flags(workspace)
    return (f"dropped the command-line settings kept on top of {PIPELINE_FILE}: "
            f"{describe_flags(flags)} (runs made with them are kept; the same settings on a "
            "command line make their run current again)")


def plan_pipeline_file(workspace: Path, path: Path, save: bool) -> Planned:
    """`sefa run PIPELINE`: the file's settings, which replace the command-line ones. They become
    the workspace's sefa.yaml when it has none; a sefa.yaml with other settings is replaced only
    with --save (the old one kept as sefa.yaml.bak), else the command stops before any work."""
    if not path.is_file():
        raise SefaInputError("no such pipeline file" if not path.exists()
                             else "is not a file (a pipeline YAML expected)", file=str(path))
    pipe = load_pipeline(workspace, path)
    target = workspace / PIPELINE_FILE
    current = load_pipeline(workspace) if target.exists() else None
    notes = []
    write = current is None or (save and asdict(current) != asdict(pipe))
    if current is not None and asdict(current) != asdict(pipe) and not save:
        raise SefaInputError(
            f"has other settings than {path} ({_first_change(asdict(current), asdict(pipe))}); "
            f"`sefa run {path} --save` replaces it (the old one kept as {PIPELINE_FILE}.bak), "
            f"`sefa run` runs it as it is", file=str(target))
    if write and current is not None:
        notes.append(f"{PIPELINE_FILE} replaced by {path}'s settings (the old one: "
                     f"{PIPELINE_FILE}.bak)")
    old = load_flags(workspace)
    if old:
        notes.append(f"{path} replaces the command-line settings ({describe_flags(old)})")

    def keep() -> None:
        workspace.mkdir(parents=True, exist_ok=True)
        if write:
            save_pipeline(workspace, pipe)
        drop_flags(workspace)
    return Planned(pipe, {}, notes, keep)


def _first_change(old: dict, new: dict, prefix: str = "") -> str:
    for key in list(old) + [k for k in new if k not in old]:
        a, b = old.get(key), new.get(key)
        if isinstance(a, dict) and isinstance(b, dict):
            if a != b:
                return _first_change(a, b, f"{prefix}{key}.")
        elif a != b:
            return f"{prefix}{key}: {a!r} here, {b!r} there"
    return "none"


def drop_flags(workspace: Path) -> None:
    """An explicit pipeline file replaces whatever the command line had set."""
    _flags_path(workspace).unlink(missing_ok=True)


def out_train_config(workspace: Path, new_flags: dict[str, Any], device: str | None):
    """`sefa train --out DIR`: the config `sefa train` would use in this workspace (sefa.yaml,
    the kept command-line settings, this command's, the machine's defaults), its store, and
    lines saying where it came from. Nothing of the workspace is written: the run is DIR's."""
    from sefa_pipelines.stages import STORE, stage_device
    from sefa_model.train.limits import check_batch

    planned = plan_settings(workspace, new_flags)
    pipe, defaults = machine_defaults(workspace, planned.pipe, device)
    cfg = base_train_config(workspace, pipe)
    cfg.training.device = stage_device(pipe, cfg, device)
    store = Path(cfg.dataset) if Path(cfg.dataset).is_absolute() else workspace / cfg.dataset
    observed = []
    if store.exists():
        from sefa_pipelines.stages import observation_notes
        from sefa_model.distributed import context

        check_batch(cfg, store, world=context().world)
        observed, _ = observation_notes(cfg, store)
    kept = describe_flags(load_flags(workspace))
    if (workspace / PIPELINE_FILE).exists():
        where = f"the settings of {workspace / PIPELINE_FILE}" + (f" with {kept}" if kept else "")
    else:
        where = (f"no {PIPELINE_FILE} in {workspace}: the defaults"
                 + (f" with {kept}" if kept else ""))
    mine = describe_flags(new_flags)
    notes = [f"--out trains with {where}" + (f", and this command's {mine}" if mine else "")]
    return cfg, store, notes + defaults + observed


def machine_defaults(workspace: Path, pipe: PipelineConfig, device: str | None) -> tuple[PipelineConfig, list[str]]:
    """Without an accelerator, the small MLP head unless the config names a head: a U-Net
    takes hours on a laptop's CPU for what the MLP learns in minutes on low-dim Push-T."""
    named = any(o.startswith("policy.head=") for o in pipe.train)
    if pipe.train_config and not named:
        named = "head" in ((load_yaml(pipe.train_config) or {}).get("policy") or {})
    if named:
        return pipe, []
    from sefa_model.distributed import resolve_device

    name = device or pipe.device or "auto"
    try:
        kind = resolve_device(name).type
    except SefaInputError:
        return pipe, []  # the stage reports the bad device itself
    if kind != "cpu":
        return pipe, []
    pipe = from_dict(PipelineConfig, {**asdict(pipe), "train": pipe.train + ["policy.head=mlp"]})
    return pipe, ["no GPU: the base policy uses the small MLP head (policy.head=mlp); name a "
                  "head in sefa.yaml's train (e.g. policy.head=unet) to choose"]


# --- upstream stages -----------------------------------------------------------------------------

def describe_stage(stage: Stage, device: str) -> str:
    """What running a stage means, in a few words (for the announcement)."""
    cfg = stage.config
    if "train" in cfg and isinstance(cfg["train"], dict) and stage.name == "train":
        t, p = cfg["train"]["training"], cfg["train"]["policy"]
        return (f"trains the base policy ({p['head']} head, {t['max_steps']} steps, batch "
                f"{t['batch_size']}, on {device})")
    if stage.name.startswith("reflow"):
        c = cfg["couplings"]
        windows = "every training window" if c["max_windows"] is None else f"{c['max_windows']} windows"
        what = (f"generates {c['samples_per_window']} couplings per window for {windows} "
                f"({c['solver']})")
        if cfg.get("reflowed_flow"):
            t = cfg["reflowed_flow"]["training"]
            what = f"trains a reflowed flow ({t['max_steps']} steps) and " + what
        return what
    if stage.name == "align":
        rule = cfg.get("replace_fraction")
        return (f"aligns the couplings (eps {cfg['eps']})" if rule is None else
                f"aligns the couplings (eps chosen to replace the nearest {rule:.0%})")
    if stage.name == "distill":
        k = cfg["train"]["flow"]["steps"]
        who = "the one-step policy" if k == 1 else f"a {k}-step student"
        return f"trains {who} ({cfg['train']['training']['max_steps']} steps)"
    return "runs"


def upstream_work(ws: Workspace, chosen: list[Stage], targets: set[str]) -> list[tuple[Stage, str]]:
    """The stages outside `targets` that a run of `chosen` would build (not cached, no kept
    run of the same settings), with the reason."""
    work = []
    for stage, (_, state, reason) in zip(chosen, pipeline_status(ws, chosen)):
        if command_of(stage) in targets or state == "cached":
            continue
        if "a kept run matches" in reason:
            continue
        work.append((stage, reason))
    return work


def _device_words(name: str) -> str:
    from sefa_model.distributed import resolve_device

    try:
        return str(resolve_device(name))
    except SefaInputError:
        return name


def confirm_upstream(command: str, work: list[tuple[Stage, str]], device: str, yes: bool,
                     interactive: bool) -> None:
    """Stop with one line naming the upstream work, unless `yes` or the user agrees."""
    if not work or yes:
        return
    what = "; ".join(f"{s.name} ({reason}): {describe_stage(s, device)}" for s, reason in work)
    first = command_of(work[0][0])
    if interactive:
        import typer

        print(f"`sefa {command}` must first run {what}", file=sys.stderr)
        if typer.confirm("run them now?", default=False, err=True):
            return
    raise SefaInputError(f"`sefa {command}` must first run {what}. Run `sefa {first}` first, or "
                         f"pass --yes (or use `sefa run`) to run it now")


def check_store(workspace: Path, command: str) -> None:
    """A workspace command needs the store first: said before anything is printed or kept."""
    from sefa_pipelines.stages import STORE

    if not (workspace / STORE).exists():
        where = "" if workspace.is_dir() else f" (no folder {workspace})"
        raise SefaInputError(f"no episode store in this workspace{where}: `sefa ingest "
                             f"RECORDINGS -w {workspace}` makes it, then `sefa {command}`",
                             file=str(workspace / STORE))


def check_ready(workspace: Path, ws: Workspace, command: str, chosen: list[Stage]) -> None:
    """What stops a command before anything else, each in its own words: no store yet (an
    empty or mistyped folder: nothing is created in it), or a run in progress."""
    check_store(workspace, command)
    holder = ws.lock_holder()
    building = running_stage(workspace, chosen) if holder is not None else None
    if building is not None:  # else the lock's own refusal says who holds it
        raise SefaInputError(f"{building} is running (pid {holder}) in this workspace: "
                             f"`sefa {command}` can start once it ends (`sefa status` shows it)")


def running_stage(workspace: Path, chosen: list[Stage]) -> str | None:
    """The stage whose build folder changed last: what the run holding the lock builds."""
    folders = [(p.stat().st_mtime, stage.name) for stage in chosen
               for p in partial_runs(workspace, stage.artifact)]
    return max(folders)[1] if folders else None


def partial_runs(workspace: Path, artifact: str) -> list[Path]:
    runs = workspace / "runs" / artifact
    return sorted(runs.glob(".*.partial")) if runs.is_dir() else []


def resumable_run(workspace: Path, stage: Stage) -> Path | None:
    """The interrupted run of exactly this stage's settings and inputs, if one was kept."""
    ws = Workspace(workspace)
    inputs = ws.input_fingerprints(stage)
    partial = ws.partial_dir(stage.artifact, run_id(stage, inputs))
    return partial if partial.is_dir() else resumable_partial(ws, stage, inputs)


def continuable_run(workspace: Path, stage: Stage) -> Path | None:
    """The finished run that a build of this stage would continue (the same settings, fewer
    steps; see pipelines/stages.py longer_run), if any."""
    ws = Workspace(workspace)
    found = ws.extension(stage, ws.input_fingerprints(stage))
    return found[0] if found is not None and found[1].allowed else None


def run_command(workspace: Path, pipe: PipelineConfig, force: set[str], *, command: str,
                yes: bool, interactive: bool, log: Log, on_step, device: str | None,
                record: dict[str, Any],
                check: Callable[[list[Stage]], None] = lambda chosen: None,
                keep: Callable[[], None] = lambda: None,
                training_notes: list[str] = (), resume: bool = False) -> list:
    """Build the stage list, stop on unannounced upstream work, run the rest. `sefa run` runs
    every stage; a stage command (train, reflow, align, distill) its own and those they read.
    `keep` (what the command writes of its settings) runs under the lock, after every check.
    `training_notes` (machine_defaults') are said only when the base policy will train.
    `resume`: a training also continues a shorter finished run whose schedule differs."""
    from sefa_pipelines.stages import base_train_config, check_fits, stage_device

    target = None if command == "run" else command
    base = base_train_config(workspace, pipe)  # read and checked once, for every use below
    chosen, forced = select(stages(workspace, pipe, log, on_step, device, resume, base=base),
                            stage_graph(pipe), target, force)
    ws = Workspace(workspace, record=record)
    ws.hashes.held = True
    from sefa_model.distributed import context

    ctx = context()
    error = None
    if ctx.is_main:
        try:
            check_ready(workspace, ws, command, chosen)
            dev = _device_words(stage_device(pipe, base, device))
            # a cached stage trains nothing: only the batches of stages that will build are checked
            building = {command_of(s) for s, (_, state, _) in zip(chosen, pipeline_status(ws, chosen))
                        if state != "cached" or s.name in forced}
            check_fits(workspace, pipe, building, device, base=base)
            confirm_upstream(command, upstream_work(ws, chosen, {target}), dev, yes, interactive)
            check(chosen)
            for note in training_notes if "train" in building else ():
                log(note)
        except SefaInputError as e:
            error = e
    # under torchrun every rank stops with rank 0, rather than waiting for it forever
    error = ctx.broadcast(None if error is None else error.line())
    if error is not None:
        raise SefaInputError(error)
    if not ctx.is_main:
        ws.hashes.held = False
        return run_pipeline(ws, chosen, force=forced, log=log)
    with ws.lock(), _saying_what_was_kept(command, chosen):
        keep()  # under the lock: a command refused by it keeps nothing of its settings
        ws.hashes.held = False
        ws.hashes.save()
        return run_pipeline(ws, chosen, force=forced, log=log)


@contextmanager
def _saying_what_was_kept(command: str, chosen: list[Stage]):
    """A Ctrl-C that left a run to continue ends with the line saying which and how; one that
    came before a training's first checkpoint says that nothing of it was kept."""
    try:
        yield
    except KeyboardInterrupt as e:
        kept, lost = getattr(e, "kept", None), getattr(e, "lost", None)
        if kept is not None:
            stage = next(s for s in chosen if s.name == kept.stage)
            e.line = interrupted_line(kept, command, command_of(stage))  # type: ignore[attr-defined]
        elif lost is not None:
            e.line = (f"interrupted: {lost}; `sefa {command}` starts it over"  # type: ignore[attr-defined]
                      " (the finished stages before it are kept)")
        raise


def interrupted_line(kept: KeptRun, command: str, builds: str) -> str:
    """`interrupted: kept runs/train/.<id>.partial at step 200 of 1000 ...; sefa train continues
    it`: what an interrupt kept and the commands that continue or drop it."""
    again = f"`sefa {command}`" + (" (it resumes)" if command != "run" else "")
    return (f"interrupted: kept {kept.words()} (not a complete artifact); continue with {again}, "
            f"or `sefa {builds} --force` to start over")


def resume_note(workspace: Path, stage: Stage) -> KeptRun | None:
    """The interrupted build of exactly this stage's settings and inputs, if one was kept
    (`sefa status`'s "interrupted at step ...")."""
    ws = Workspace(workspace)
    return kept_run_of(ws, stage, ws.partial_dir(stage.artifact,
                                                 run_id(stage, ws.input_fingerprints(stage))))


# --- sefa config set ------------------------------------------------------------------------------

def set_setting(workspace: Path, key: str, value: str) -> str:
    """`sefa config set KEY VALUE`: one setting of sefa.yaml (`reflow.train_steps 200`), or of the
    base policy's train config (`train.training.max_steps 2000`, kept in sefa.yaml's `train`
    list). The new file is checked the way the commands that read it check it (the typed
    configs, the train config file it names, the device, the batches against the store's data
    and observation keys, with the command-line settings kept on top) before anything is
    written; then written atomically (the old file kept as sefa.yaml.bak) under the workspace
    lock, only that one value changed: comments, order and a symlink are kept (ruamel.yaml's
    round trip: PyYAML drops comments). Returns the line to print."""
    from sefa_pipelines.stages import pipeline_from_data, write_pipeline_text
    from sefa_data.config_io import parse_value, parse_yaml

    if not key or "=" in key or any(not part for part in key.split(".")):
        raise SefaInputError(f"'{key}' is not a dotted key (e.g. reflow.train_steps, "
                             f"train.training.max_steps)", key=key or "KEY")
    if not workspace.is_dir():
        raise SefaInputError("no such workspace folder", file=str(workspace))
    parsed = parse_value(value, key)
    pipe = load_pipeline(workspace)
    path = workspace / PIPELINE_FILE
    doc, dump = _round_trip(path)
    head, _, rest = key.partition(".")
    if head == "train" and rest:
        _set_override(doc, rest, value)
    elif head == "train" or isinstance(asdict(pipe).get(head), list):
        raise SefaInputError(f"'{key}' is a list; set one of its keys instead (e.g. "
                             f"train.training.max_steps)", key=key)
    else:
        _set_path(doc, key, parsed)
    text = dump(doc)
    # errors name the key alone: sefa.yaml does not hold the refused value
    new = pipeline_from_data(parse_yaml(text, f"sefa config set {key}"), path, None)
    check_setting(workspace, new, key)
    old_value = _lookup(asdict(pipe), key)
    with Workspace(workspace).lock():
        write_pipeline_text(workspace, text)
    line = f"{PIPELINE_FILE}: {key} = {value} (was {'null' if old_value is None else old_value})"
    flags = load_flags(workspace)
    shadow = (_lookup({"train": flags.get("train", [])}, key) if head == "train" else
              _lookup(flags, key))
    if shadow not in ("unset", "the default"):
        line += (f"; the command-line setting {key}={shadow} kept in {_flags_path(workspace)} "
                 f"still applies on top of it (`sefa {head if head in SECTIONS else 'train'} "
                 f"... --save` folds such settings into {PIPELINE_FILE})")
    return line


def check_setting(workspace: Path, cfg: PipelineConfig, key: str) -> None:
    """What `sefa train`, `reflow`, `distill` and `status` check before they start, on the
    settings they would run with (`cfg` with the kept command-line settings on top): the train
    config file and its overrides, the device name, and, with a store, every training's batch
    against its data and memory and the observation keys against the store's. A refusal names
    `key` where the check's own line names no key."""
    from sefa_pipelines.stages import check_fits, stage_device

    try:
        effective = apply_flags(cfg, load_flags(workspace), str(_flags_path(workspace)))
        base = base_train_config(workspace, effective)
        stage_device(effective, base)
        check_fits(workspace, effective, {"train", "reflow", "distill"}, base=base)
    except SefaInputError as e:
        if e.key is None:
            raise SefaInputError(e.what, file=e.file, key=key, where=e.where) from None
        raise


def _round_trip(path: Path):
    """(sefa.yaml as ruamel.yaml's round-trip document, a function that dumps one to text)."""
    import io

    from ruamel.yaml import YAML
    from ruamel.yaml.comments import CommentedMap

    y = YAML()  # round trip: comments, key order and quoting are kept
    y.preserve_quotes = True
    y.width = 4096  # never fold a long line that was one line
    doc = y.load(path.read_text()) if path.exists() else None

    def dump(d) -> str:
        out = io.StringIO()
        y.dump(d, out)
        return out.getvalue()
    return (doc if doc is not None else CommentedMap()), dump


def _set_path(doc, key: str, value: Any) -> None:
    from ruamel.yaml.comments import CommentedMap

    node = doc
    *parents, last = key.split(".")
    for part in parents:
        if not isinstance(node.get(part), dict):
            node[part] = CommentedMap()  # a missing or null section; from_dict checks the rest
        node = node[part]
    node[last] = value


def _set_override(doc, rest: str, value: str) -> None:
    """`train` holds key=value overrides: the item of that key replaced where it stands (its
    comment kept), later duplicates dropped; else appended."""
    from ruamel.yaml.comments import CommentedSeq

    items = doc.get("train")
    if not isinstance(items, list):
        items = doc["train"] = CommentedSeq()
    item = f"{rest}={value}"
    same = [i for i, o in enumerate(items) if isinstance(o, str) and o.split("=", 1)[0] == rest]
    if not same:
        items.append(item)
        return
    items[same[0]] = item
    for i in reversed(same[1:]):
        del items[i]


def _lookup(data: dict, key: str) -> Any:
    head, _, rest = key.partition(".")
    if head == "train" and rest:
        found = [o.split("=", 1)[1] for o in data["train"] if o.split("=", 1)[0] == rest]
        return found[-1] if found else "the default"
    node: Any = data
    for part in key.split("."):
        if not isinstance(node, dict) or part not in node:
            return "unset"
        node = node[part]
    return node
