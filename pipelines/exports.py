"""The exports made from a workspace's checkpoints, and whether each still matches its stage.

    WORKSPACE/.sefa/exports/<id>.json    one per export directory: {"out", "checkpoint",
                                         "command"}

`sefa export CKPT --out DIR` records DIR here when CKPT lies in the workspace (`distill`, a
stage's pointer, or a run folder). The export's own metadata.json holds the digest of the
checkpoint it came from (`checkpoint_digest`); `sefa status` compares it with the digest of
what CKPT names now: a stage that retrained has moved its pointer to another run, so an export
made before is stale, and the status says which command makes it again. The record holds no
digest itself: the export directory is the truth (exported again elsewhere or by hand, it is
what metadata.json says).
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any

from sefa_pipelines.evals import label
from sefa_pipelines.runner import STATE_DIR
from sefa_pipelines.stages import STORE
from sefa_data import atomic
from sefa_data.errors import SefaInputError

EXPORTS_DIR = "exports"


def _records(workspace: Path) -> Path:
    return workspace / STATE_DIR / EXPORTS_DIR


def record_export(workspace: Path, checkpoint: Path, out: Path, command: str) -> bool:
    """Remember an export of a checkpoint of `workspace`; False (nothing recorded) for a
    checkpoint outside it or a folder that is no workspace."""
    root = Path(os.path.realpath(workspace))
    if not (root / STORE).exists() or not Path(os.path.realpath(checkpoint)).is_relative_to(root):
        return False
    out = Path(os.path.abspath(out))
    folder = _records(workspace)
    folder.mkdir(parents=True, exist_ok=True)
    name = hashlib.sha256(str(out).encode()).hexdigest()[:12] + ".json"  # one per directory
    atomic.write_json(folder / name, {"out": str(out), "checkpoint": label(workspace, checkpoint),
                                      "command": command})
    return True


def _run(workspace: Path, checkpoint: str | Path | None) -> str:
    """The run folder a checkpoint lies in, as the workspace names it (pointers resolved)."""
    if not checkpoint:
        return "?"
    path = label(Path(os.path.realpath(workspace)), Path(os.path.realpath(checkpoint)))
    return path.removesuffix("/checkpoints/latest")


def export_rows(workspace: Path) -> list[dict[str, Any]]:
    """One `sefa status` row per recorded export that still exists: done while the checkpoint
    it came from is what its path names now, else stale with the command that exports again."""
    from sefa_deploy.metadata import load_metadata
    from sefa_model.policy.checkpoint import checkpoint_digest, resolve_checkpoint

    folder = _records(workspace)
    rows = []
    for path in sorted(folder.glob("*.json")) if folder.is_dir() else []:
        try:
            rec = json.loads(path.read_text())
            meta = load_metadata(rec["out"])
        except (OSError, ValueError, KeyError, TypeError, SefaInputError):
            continue  # the export was deleted or replaced by something else: nothing to track
        row = {"stage": "export", "path": label(workspace, Path(rec["out"])), "duration": None,
               "metric": f"{meta.get('format')} of {rec['checkpoint']} "
                         f"({_run(workspace, meta.get('checkpoint_resolved'))})"}
        try:
            now = resolve_checkpoint(workspace / rec["checkpoint"])
            current = checkpoint_digest(now)
        except SefaInputError:
            now, current = None, None
        same = current is not None and current == meta.get("checkpoint_digest")
        changed = _execution_changed(now, meta) if same else None
        if same and changed is None:
            rows.append({**row, "state": "done", "reason": None})
            continue
        what = ("is gone" if now is None else changed if same
                else f"was made again since: now {_run(workspace, now)}")
        rows.append({**row, "state": "stale", "command": rec["command"],
                     "reason": f"{rec['checkpoint']} {what}; export again: {rec['command']}"})
    return sorted(rows, key=lambda r: r["path"])


def _execution_changed(checkpoint: Path, meta: dict) -> str | None:
    """Why an export no longer runs the execution chosen for its checkpoint (`sefa
    choose-execution` chose another since), or None; an export made with --execution keeps
    what it was given. None recorded means receding over n_action_steps, which a choice of the
    same does not change."""
    from sefa_model.policy.execution import ExecutionSettings, default_settings, load_choice

    if meta.get("execution_source") == "given":
        return None
    setting = meta.get("solver") if meta.get("steps") is None else f"{meta.get('solver')}-{meta['steps']}"
    try:
        chosen = load_choice(checkpoint, setting)
        n = meta["n_action_steps"]
        runs = (default_settings(n) if not meta.get("execution")
                else ExecutionSettings.from_json(meta["execution"]).resolved(n))
        now = default_settings(n) if chosen is None else chosen.resolved(n)
    except (SefaInputError, KeyError, TypeError) as e:
        return f"has an execution record or export metadata that cannot be read ({e})"
    if now == runs:
        return None
    return (f"has another execution chosen since: {now.label}, where the export runs "
            f"{runs.label}")
