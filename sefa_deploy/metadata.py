"""An export's contract with its caller: `metadata.json` (what `build_metadata` writes and
`load_metadata` reads back), the artifact's file name per format, and the frame rate found in
the policy's store.

`sefa export` writes it beside the artifact (sefa_deploy.export); every serving backend
(sefa_deploy.backends) answers with the same dict, a checkpoint served directly included;
`sefa status` reads it to tell a stale export (sefa_pipelines.exports). Its own module so that the
exporter and the backends it checks its artifact with both import it, not each other.

An export is served only as it was written: `sefa export` records the size and SHA-256 of
metadata.json and the artifact in `checksums.json` (as a checkpoint records its files), and
`open_export` checks them, then that metadata.json agrees with itself (the output and noise
shapes with n_action_steps, horizon and action_dim; the executed slice; the inputs); the
serving backend then runs the artifact once on zeros of the shapes it names
(sefa_deploy.backends.load_backend). An edited or damaged export is refused in one line at
load, never served to fail on every request.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import TYPE_CHECKING

from sefa_data.errors import SefaInputError
from sefa_model.policy.checkpoint import checkpoint_digest, verify_checksums

if TYPE_CHECKING:
    from sefa_model.policy.artifact import Policy
    from sefa_model.policy.execution import ExecutionSettings

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
                   fps: float | None, execution: ExecutionSettings | None = None) -> dict:
    """The artifact's contract with its caller; `sefa serve` answers a metadata call with it
    (fmt "checkpoint" when it serves a checkpoint directly). `execution`: the one asked for
    (`sefa export --execution ...`), else the one chosen for the policy is recorded."""
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
        # how chunks become one action per step (sefa_model/policy/execution.py): the one asked
        # for at export ("given") or chosen for this policy at this setting ("chosen"); None:
        # neither, receding over n_action_steps ("default"). `sefa status` calls an export of
        # a chosen or default execution stale once another is chosen.
        **execution_fields(policy, solver, steps, execution),
    }


def execution_fields(policy: Policy, solver: str, steps: int | None,
                     execution: ExecutionSettings | None) -> dict:
    if execution is not None:
        settings = execution.resolved(policy.cfg.policy.n_action_steps)
        return {"execution": settings.to_json(), "execution_source": "given"}
    chosen = recorded_execution(policy, solver, steps)
    return {"execution": chosen, "execution_source": "default" if chosen is None else "chosen"}


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


def open_export(directory: str | Path) -> dict:
    """An export's metadata, once its checksums (where it has them: exports written before them
    have none) and its own consistency check out; one SefaInputError naming the file otherwise."""
    directory = Path(directory)
    meta = load_metadata(directory)
    verify_checksums(directory, what="export")
    check_metadata(meta, directory / METADATA_FILE)
    return meta


def _shape(meta: dict, *keys: str) -> list:
    value = meta
    for k in keys:
        value = value[k]
    return list(value)


def check_metadata(meta: dict, path: Path) -> None:
    """The fields metadata.json derives from n_obs_steps, n_action_steps, horizon and
    action_dim must say what build_metadata wrote from them: a hand edit of one is refused."""
    try:
        n_obs, n_act, horizon, dim = (int(meta[k]) for k in ("n_obs_steps", "n_action_steps",
                                                             "horizon", "action_dim"))
        derived = [  # (key, as written, as derived, derived from)
            ("outputs.action.shape", _shape(meta, "outputs", "action", "shape"), [n_act, dim],
             f"n_action_steps {n_act} and action_dim {dim}"),
            ("outputs.action_pred.shape", _shape(meta, "outputs", "action_pred", "shape"),
             [horizon, dim], f"horizon {horizon} and action_dim {dim}"),
            ("noise.shape", _shape(meta, "noise", "shape"), [horizon, dim],
             f"horizon {horizon} and action_dim {dim}"),
            ("execute", [meta["execute"]["start"], meta["execute"]["stop"]],
             [n_obs - 1, n_obs - 1 + n_act], f"n_obs_steps {n_obs} and n_action_steps {n_act}"),
            ("inputs", list(meta["inputs"]), [*meta["obs"], "noise"], "obs"),
            *[(f"obs.{k}.shape", _shape(v, "shape")[:1], [n_obs], f"n_obs_steps {n_obs}")
              for k, v in meta["obs"].items()],
        ]
    except (KeyError, TypeError, ValueError, IndexError) as e:
        raise SefaInputError(f"malformed export metadata ({type(e).__name__}: {e}); export "
                             "again", file=str(path)) from None
    for key, got, want, basis in derived:
        if got != want:
            raise SefaInputError(
                f"{basis} make {key} {want}, but it is {got}: the file was edited after the "
                "export (a policy's shapes are fixed when it is exported); export again",
                file=str(path))
