"""Evaluations that last: each result in its own folder, cached by what it depends on.

    WORKSPACE/evals/<mode>-<key>/result.json     (and eval_log.json for rollouts)

`key` hashes the checkpoint's content (every file of the checkpoint directory) and the
evaluation's settings (solver, steps, seeds, windows, ...), so the same evaluation asked twice is
read back at once, different seeds or solvers sit side by side, and a retrained checkpoint is
evaluated anew. Paths are recorded relative to the workspace. A result folder is written under a
temporary name and renamed into place.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Callable

from pipelines.runner import STATE_DIR, FileHashCache, canonical_json, path_sha256
from sefa_data import atomic

EVALS_DIR = "evals"
RESULT = "result.json"


def checkpoint_sha256(workspace: Path, checkpoint: Path) -> str:
    from sefa_model.checkpoint import resolve_checkpoint

    cache = FileHashCache(workspace.absolute() / STATE_DIR / "file_hashes.json")
    try:
        return path_sha256(resolve_checkpoint(checkpoint), cache)
    finally:
        cache.save()


def label(workspace: Path, path: Path) -> str:
    """A path as the workspace names it: relative when inside, else absolute."""
    try:
        return Path(os.path.abspath(path)).relative_to(workspace.absolute()).as_posix()
    except ValueError:
        return str(Path(path).absolute())


def eval_key(checkpoint_sha: str, mode: str, settings: dict[str, Any]) -> str:
    text = canonical_json({"checkpoint": checkpoint_sha, "mode": mode, "settings": settings})
    return hashlib.sha256(text.encode()).hexdigest()[:12]


def eval_dir(workspace: Path, mode: str, key: str) -> Path:
    return workspace / EVALS_DIR / f"{mode.replace(':', '_')}-{key}"


def cached_eval(workspace: Path, checkpoint: Path, mode: str, settings: dict[str, Any],
                run: Callable[[Path], dict[str, Any] | None], *, force: bool = False,
                is_main: bool = True) -> tuple[dict[str, Any] | None, bool]:
    """(the result record, whether it was computed now). `run(folder)` evaluates, may write
    files into `folder`, and returns the result (None on ranks other than 0)."""
    sha = checkpoint_sha256(workspace, checkpoint)
    key = eval_key(sha, mode, settings)
    final = eval_dir(workspace, mode, key)
    cached = read_result(final)
    if cached is not None and not force:
        return cached, False
    tmp = atomic.tmp_name(final)
    if is_main:
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir(parents=True)
    try:
        started = time.monotonic()
        result = run(tmp)
        if not is_main or result is None:
            return None, True
        real = os.path.realpath(checkpoint)
        record = {
            "mode": mode, "key": key, "settings": settings,
            "checkpoint": label(workspace, checkpoint), "checkpoint_run": label(workspace, Path(real)),
            "checkpoint_sha256": sha,
            "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "duration_s": round(time.monotonic() - started, 3),
            "result": _relative(result, workspace, tmp, final),
        }
        (tmp / RESULT).write_text(json.dumps(record, indent=2) + "\n")
        atomic.replace_dir(tmp, final)
        return record, True
    except BaseException:
        if is_main:
            shutil.rmtree(tmp, ignore_errors=True)
        raise


def _relative(value: Any, workspace: Path, tmp: Path, final: Path) -> Any:
    if isinstance(value, dict):
        return {k: _relative(v, workspace, tmp, final) for k, v in value.items()}
    if isinstance(value, list):
        return [_relative(v, workspace, tmp, final) for v in value]
    if isinstance(value, str) and os.path.isabs(value):
        if value.startswith(str(tmp)):
            value = str(final) + value[len(str(tmp)):]
        return label(workspace, Path(value))
    return value


def read_result(folder: Path) -> dict[str, Any] | None:
    try:
        value = json.loads((folder / RESULT).read_text())
    except (OSError, ValueError):
        return None
    return value if isinstance(value, dict) else None


def all_results(workspace: Path) -> list[dict[str, Any]]:
    """Every evaluation kept in the workspace, oldest first, each with its folder."""
    root = workspace / EVALS_DIR
    rows = []
    for folder in sorted(root.iterdir()) if root.is_dir() else []:
        if folder.name.startswith("."):
            continue
        record = read_result(folder)
        if record is not None:
            rows.append({**record, "folder": label(workspace, folder)})
    return sorted(rows, key=lambda r: r.get("created", ""))


def key_metric(record: dict[str, Any]) -> str:
    r = record["result"]
    if record["mode"] == "offline":
        return (f"action MSE {r['action_mse']:.4g}, spread ratio {r['spread_ratio']:.2f} "
                f"({r['windows']} {r['split']} windows)")
    return (f"mean score {r['test/mean_score']:.3f}, success {r['test/success_rate']:.0%} "
            f"({r['n_test']} seeds from {r['test_start_seed']})")
