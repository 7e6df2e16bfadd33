"""What `sefa status` and `sefa config show` report about a workspace."""

from __future__ import annotations

import os
from dataclasses import asdict
from pathlib import Path
from typing import Any

from sefa_pipelines.runner import Workspace, pipeline_status, run_id
from sefa_pipelines.workspace import resume_note
from sefa_pipelines.stages import PIPELINE_FILE, STORE, base_train_config, command_of, stages


def _settings(workspace: Path):
    from sefa_pipelines.workspace import machine_defaults, settings

    pipe, flags, notes = settings(workspace, write=False)
    pipe, defaults = machine_defaults(workspace, pipe, None)
    return pipe, flags, notes + defaults


def resolved_config(workspace: Path) -> dict[str, Any]:
    from sefa_model.config import config_to_dict
    from sefa_pipelines.stages import load_pipeline

    pipe, flags, notes = _settings(workspace)
    return {"sefa.yaml": asdict(load_pipeline(workspace)), "command_line": flags, "notes": notes,
            "resolved": asdict(pipe), "train": config_to_dict(base_train_config(workspace, pipe))}


def format_duration(seconds: float) -> str:
    seconds = int(round(seconds))
    h, rest = divmod(seconds, 3600)
    m, s = divmod(rest, 60)
    return f"{h}h{m:02d}m{s:02d}s" if h else f"{m}m{s:02d}s" if m else f"{s}s"


def stage_metric(name: str, summary: dict[str, Any] | None) -> str | None:
    """The one number worth seeing per stage."""
    if not summary:
        return None
    val = summary.get("val") or (summary.get("flow") or {}).get("val") or {}
    if name in ("train", "distill") or (name.startswith("reflow") and summary.get("flow")):
        loss = summary.get("train_loss", (summary.get("flow") or {}).get("train_loss"))
        # None: the run resumed at its last step and trained none
        text = "train loss " + ("-" if loss is None else f"{loss:.4g}")
        if val.get("val_action_mse") is not None:
            text += (f", val action MSE {val['val_action_mse']:.4g} (mean action "
                     f"{val['val_mean_action_mse']:.4g})")
        if name.startswith("reflow"):
            c = summary.get("couplings") or {}
            text += f"; {c.get('n')} couplings"
        if name == "distill" and distill_alignment(summary):
            text += f"; {distill_alignment(summary)}"
        return text
    if name.startswith("reflow"):
        c = summary.get("couplings") or {}
        return (f"{c.get('n')} couplings of {c.get('windows')} windows, "
                f"{c.get('evals_per_coupling', 0):.0f} evals per coupling")
    if name == "align":
        from sefa_pipelines.report import eps_words

        return (f"replaced {summary.get('fraction_replaced', 0):.1%} of {summary.get('n')} "
                f"({eps_words(summary)})")
    return None


def distill_alignment(summary: dict[str, Any]) -> str:
    """What the student trained on (issue 25: an alignment that replaced nothing is said)."""
    a = summary.get("alignment")
    if summary.get("kind") == "reflow_one_step" and not a:
        return "unaligned couplings (plain reflow)"
    if not a:  # a student distilled before this was recorded
        return ""
    if not a["n_replaced"]:
        return f"aligned 0% (eps {a['eps']:.4g}): plain reflow"
    return f"aligned {a['fraction_replaced']:.1%} (eps {a['eps']:.4g})"


def _store_row(workspace: Path) -> dict[str, Any]:
    path = workspace / STORE
    row = {"stage": "ingest", "path": STORE, "duration": None, "reason": None}
    if not path.exists():
        return {**row, "state": "missing", "path": None, "metric": None,
                "reason": "no store: sefa ingest RECORDINGS -w WORKSPACE"}
    import zarr

    from sefa_data.store.integrity import mask_group

    try:
        root = zarr.open_group(str(path), mode="r")
        ends = root["meta/episode_ends"][:]
        masks = mask_group(root)
        train, valid = (int(masks[k][:].sum()) for k in ("train", "valid"))
    except Exception as e:  # a damaged store: `sefa inspect` says what is wrong
        return {**row, "state": "damaged", "metric": None,
                "reason": f"{type(e).__name__}: `sefa inspect {path}` for details"}
    metric = (f"{len(ends)} episodes, {int(ends[-1]) if len(ends) else 0} frames, split "
              f"{train} train / {valid} valid episodes"
              + (" (a window-level split at training)" if valid == 0 else ""))
    return {**row, "state": "done", "metric": metric}


def eval_hint(workspace: Path, pipe) -> str:
    """`sefa eval --offline`, and `--env` only for a simulator that gives the policy's
    observations (a KUKA policy has none)."""
    from sefa_pipelines.evals import rollout_envs
    from sefa_data.store.zarr_store import EpisodeStore
    from sefa_model.policy.model import observation_keys

    store = EpisodeStore.open(workspace / STORE)
    used, _ = observation_keys(base_train_config(workspace, pipe), store)
    envs = [_named_task(env, store) for env in rollout_envs(used)]
    return "sefa eval --offline" + (f" (or --env {envs[0]})" if envs else "")


def _named_task(env: str, store) -> str:
    """metaworld:TASK with the task the store's demonstrations recorded (`sefa collect` writes
    it into env_args), when they all recorded the same one."""
    from sefa_pipelines.evals import METAWORLD

    if env != METAWORLD + "TASK":
        return env
    tasks = {(src.get("reader") or {}).get("env_args", {}).get("task")
             for src in store.attrs.get("sources", []) if isinstance(src, dict)}
    return METAWORLD + tasks.pop() if len(tasks) == 1 and None not in tasks else env


def overview(workspace: Path) -> dict[str, Any]:
    from sefa_pipelines.evals import all_results, key_metric

    rows = [_store_row(workspace)]
    notes = []
    if not (workspace / STORE).exists():
        return {"notes": notes, "rows": rows, "next": "sefa ingest RECORDINGS -w " + str(workspace)}
    pipe, _, notes = _settings(workspace)
    ws = Workspace(workspace)
    stage_list = stages(workspace, pipe)
    holder = ws.lock_holder()
    running = False
    nxt = None
    for stage, (name, state, reason) in zip(stage_list, pipeline_status(ws, stage_list)):
        manifest = ws.read_manifest(stage.artifact)
        link = ws.artifact_dir(stage.artifact)
        path = (Path(os.path.realpath(link)).relative_to(ws.root).as_posix()
                if manifest is not None else None)
        cmd = f"sefa {command_of(stage)}"
        if state != "cached" and holder:
            partial = ws.partial_dir(stage.artifact, run_id(stage, ws.input_fingerprints(stage)))
            if partial.is_dir() and not running:
                state, reason, running = "running", f"being built by pid {holder}", True
                path = partial.relative_to(ws.root).as_posix()
                manifest = None  # the current run's numbers are not the running one's
            elif running:
                state, reason = "waiting", f"after the running stage (pid {holder})"
        elif state != "cached":
            kept = resume_note(workspace, stage)
            if kept is not None:  # an interrupted run of these settings, to continue
                reason = (f"{reason}; interrupted run kept: {kept.words()}, `{cmd}` continues "
                          f"it (`{cmd} --force` starts over)")
                if nxt is None:
                    nxt = f"{cmd} (continues the interrupted run: {kept.words()})"
        if state != "cached" and nxt is None:
            nxt = cmd
        rows.append({"stage": name, "state": state, "reason": reason, "path": path,
                     "metric": stage_metric(name, (manifest or {}).get("summary")),
                     "duration": format_duration(manifest["duration_s"])
                     if manifest and manifest.get("duration_s") is not None else None})
    evals = all_results(workspace)
    rows.append({"stage": "eval", "state": "done" if evals else "missing",
                 "path": "evals/" if evals else None, "reason": None if evals else
                 "no evaluation yet", "duration": None,
                 "metric": (f"{len(evals)} kept; latest: {evals[-1]['checkpoint']} "
                            f"{key_metric(evals[-1])}") if evals else None})
    from sefa_pipelines.exports import export_rows

    exports = export_rows(workspace)
    rows += exports
    stale = [r["command"] for r in exports if r["state"] == "stale"]
    if running:
        nxt = "wait for the running stage (pid " + str(holder) + "), or `sefa status` again"
    elif nxt is None and stale:
        nxt = stale[0]
    elif nxt is None:
        nxt = "sefa results" if evals else eval_hint(workspace, pipe)
    return {"notes": notes, "rows": rows, "next": nxt, "settings": PIPELINE_FILE}
