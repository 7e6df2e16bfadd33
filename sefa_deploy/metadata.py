"""An export's contract with its caller: `metadata.json` (what `build_metadata` writes and
`load_metadata` reads back), the artifact's file name per format, and the frame rate found in
the policy's store.

`sefa export` writes it beside the artifact (sefa_deploy.export); every serving backend
(sefa_deploy.backends) answers with the same dict, a checkpoint served directly included;
`sefa status` reads it to tell a stale export (sefa_pipelines.exports). Its own module so that the
exporter and the backends it checks its artifact with both import it, not each other.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import TYPE_CHECKING

from sefa_data.errors import SefaInputError
from sefa_model.policy.checkpoint import checkpoint_digest

if TYPE_CHECKING:
    from sefa_model.policy.artifact import Policy

FORMATS = {"onnx": "policy.onnx", "torchscript": "policy.pt"}
METADATA_FILE = "metadata.json"
EXPORT_FORMAT = 1
NFE_PER_STEP = {"euler": 1, "midpoint": 2, "rk4": 4}


def find_store(policy: Policy):
    """The policy's store (an EpisodeStore): the checkpoint's `dataset` as given, else looked
    for beside the checkpoint's run directories (a workspace holds dataset.zarr next to
    train/); None when there is none that opens."""
    from sefa_data.store.zarr_store import EpisodeStore

    dataset = Path(policy.cfg.dataset)
    candidates = [dataset] if dataset.is_absolute() else [
        dataset, *(parent / dataset for parent in Path(policy.path).resolve().parents)]
    for path in candidates:
        if (path / "zarr.json").exists() or (path / ".zattrs").exists() or (path / ".zgroup").exists():
            try:
                return EpisodeStore.open(path)
            except (SefaInputError, KeyError, OSError):
                continue
    return None


def find_fps(policy: Policy) -> tuple[float | None, str]:
    """The store's frame rate, and where it came from."""
    store = find_store(policy)
    if store is None:
        return None, f"store '{policy.cfg.dataset}' not found; pass --fps"
    return store.fps, str(store.path)


def build_metadata(policy: Policy, fmt: str, solver: str, steps: int | None,
                   fps: float | None) -> dict:
    """The artifact's contract with its caller; `sefa serve` answers a metadata call with it
    (fmt "checkpoint" when it serves a checkpoint directly)."""
    cfg = policy.cfg
    p, meta = cfg.policy, cfg.shape_meta
    action_dim = meta.action.shape[-1]
    start = p.n_obs_steps - 1
    obs = policy.processor.inputs(p.n_obs_steps)  # what the server checks requests against
    action_norm = policy.normalizer.params[meta.action.key]
    return {
        "sefa_export": EXPORT_FORMAT,
        "format": fmt,
        "file": FORMATS.get(fmt),  # None: served from the checkpoint itself
        "checkpoint": str(policy.path),
        "checkpoint_resolved": os.path.realpath(policy.path),  # a pointer's run folder
        "checkpoint_digest": checkpoint_digest(Path(policy.path)),
        "kind": policy.kind,
        "weights": policy.weights,  # ema.safetensors, or model.safetensors with --raw-weights
        "solver": solver,
        "steps": steps,
        # network evaluations per chunk; None: an adaptive solver, it varies with the input
        "nfe": steps * NFE_PER_STEP[solver] if solver in NFE_PER_STEP else None,
        "fps": fps,
        "n_obs_steps": p.n_obs_steps,
        "n_action_steps": p.n_action_steps,
        "horizon": p.horizon,
        "action_key": meta.action.key,
        "action_dim": action_dim,
        # the inputs' names (the store's keys) in call order (the module docstring says
        # which); the batch axis is dynamic
        "inputs": [*meta.obs, "noise"],
        "obs": obs,
        "noise": {"shape": [p.horizon, action_dim], "dtype": "float32",
                  "distribution": "standard normal"},
        "outputs": {"action": {"shape": [p.n_action_steps, action_dim], "dtype": "float32"},
                    "action_pred": {"shape": [p.horizon, action_dim], "dtype": "float32"}},
        # action == action_pred[:, start:stop]: execute these, then observe again
        "execute": {"start": start, "stop": start + p.n_action_steps},
        # normalized = action * scale + offset (per action dimension)
        "action_normalizer": {"mode": action_norm.mode, "scale": action_norm.scale.tolist(),
                              "offset": action_norm.offset.tolist()},
        # how chunks become one action per step, as chosen for this policy at this setting
        # (sefa_model/policy/execution.py); None: none chosen, receding over n_action_steps
        "execution": recorded_execution(policy, solver, steps),
    }


def recorded_execution(policy: Policy, solver: str, steps: int | None) -> dict | None:
    from sefa_model.policy.execution import load_choice

    choice = load_choice(policy.path, solver if steps is None else f"{solver}-{steps}")
    return None if choice is None else choice.to_json()


def load_metadata(directory: str | Path) -> dict:
    path = Path(directory) / METADATA_FILE
    try:
        meta = json.loads(path.read_text())
    except FileNotFoundError:
        raise SefaInputError("not a sefa export (no metadata.json)", file=str(directory)) from None
    except (ValueError, UnicodeDecodeError) as e:
        raise SefaInputError(f"corrupt JSON ({e})", file=str(path)) from None
    if not isinstance(meta, dict) or meta.get("sefa_export") != EXPORT_FORMAT:
        raise SefaInputError(f"not a sefa export metadata file of format {EXPORT_FORMAT}",
                             file=str(path))
    return meta
