"""Checkpoints without pickle: safetensors for tensors, JSON for everything else.

    <dir>/config.json             the fully resolved TrainConfig + the flow convention + kind
    <dir>/model.safetensors       raw weights
    <dir>/ema.safetensors         EMA weights (used for evaluation)
    <dir>/normalizer.safetensors  + normalizer.json
    <dir>/processor.json          the observation/action transform (sefa_model/processor.py)
    <dir>/training_state/         optimizer, scheduler, step (only what `--resume` needs)
        state.safetensors, state.json

A checkpoint directory is written under a temporary name and renamed into place, so a crash
never leaves one that looks complete.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file

from sefa_data.errors import SefaInputError
from sefa_data import atomic

CHECKPOINT_FORMAT = 1


def flatten_state(state: Any, prefix: str = "") -> tuple[Any, dict[str, torch.Tensor]]:
    """Split a nested state (dicts, lists, tensors, scalars) into JSON and named tensors."""
    tensors: dict[str, torch.Tensor] = {}

    def walk(obj: Any, path: str) -> Any:
        if isinstance(obj, torch.Tensor):
            tensors[path] = obj.detach().cpu().contiguous()
            return {"__tensor__": path}
        if isinstance(obj, dict):
            return {"__dict__": [[walk(k, f"{path}.k{i}"), walk(v, f"{path}.{i}")]
                                 for i, (k, v) in enumerate(obj.items())]}
        if isinstance(obj, (list, tuple)):
            return {"__list__": [walk(v, f"{path}.{i}") for i, v in enumerate(obj)],
                    "tuple": isinstance(obj, tuple)}
        if obj is None or isinstance(obj, (bool, int, float, str)):
            return obj
        raise TypeError(f"cannot store {type(obj).__name__} at {path} in a checkpoint")

    return walk(state, prefix or "s"), tensors


def unflatten_state(tree: Any, tensors: dict[str, torch.Tensor]) -> Any:
    if isinstance(tree, dict):
        if "__tensor__" in tree:
            return tensors[tree["__tensor__"]]
        if "__dict__" in tree:
            return {unflatten_state(k, tensors): unflatten_state(v, tensors) for k, v in tree["__dict__"]}
        if "__list__" in tree:
            items = [unflatten_state(v, tensors) for v in tree["__list__"]]
            return tuple(items) if tree.get("tuple") else items
    return tree


def save_state(directory: Path, state: Any) -> None:
    tree, tensors = flatten_state(state)
    directory.mkdir(parents=True, exist_ok=True)
    save_file(tensors, str(directory / "state.safetensors"))
    (directory / "state.json").write_text(json.dumps(tree))


def load_state(directory: Path) -> Any:
    tree = read_json(directory / "state.json")
    return unflatten_state(tree, read_tensors(directory / "state.safetensors"))


def read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise SefaInputError("missing checkpoint file", file=str(path)) from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise SefaInputError(f"corrupt JSON ({e})", file=str(path)) from None


def read_tensors(path: Path) -> dict[str, torch.Tensor]:
    if not path.exists():
        raise SefaInputError("missing checkpoint file", file=str(path))
    try:
        return load_file(str(path))
    except (SafetensorError, OSError, ValueError) as e:
        raise SefaInputError(f"corrupt safetensors file ({str(e).splitlines()[0]})",
                             file=str(path)) from None


def load_weights(module: torch.nn.Module, path: Path) -> None:
    """Load weights strictly: a checkpoint for another architecture is a clear error."""
    state = read_tensors(path)
    own = module.state_dict()
    missing = sorted(set(own) - set(state))
    unexpected = sorted(set(state) - set(own))
    if missing or unexpected:
        what = (f"missing {missing[0]}" if missing else f"unexpected {unexpected[0]}")
        raise SefaInputError(f"weights do not match the model in config.json ({what}; "
                             f"{len(missing)} missing, {len(unexpected)} unexpected)", file=str(path))
    for name, tensor in state.items():
        if tensor.shape != own[name].shape:
            raise SefaInputError(f"weights do not match the model in config.json ({name}: "
                                 f"{tuple(tensor.shape)} vs {tuple(own[name].shape)})", file=str(path))
    module.load_state_dict(state)


def write_checkpoint(directory: Path, *, config: dict, model: torch.nn.Module,
                     ema: torch.nn.Module | None, normalizer, training_state: Any | None,
                     processor: dict | None = None) -> None:
    """Write a whole checkpoint next to `directory`, then swap it into place."""
    tmp = atomic.tmp_name(directory)
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    save_file({k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()},
              str(tmp / "model.safetensors"))
    if ema is not None:
        save_file({k: v.detach().cpu().contiguous() for k, v in ema.state_dict().items()},
                  str(tmp / "ema.safetensors"))
    normalizer.save(tmp)
    if processor is not None:
        (tmp / "processor.json").write_text(json.dumps(processor, indent=1))
    if training_state is not None:
        save_state(tmp / "training_state", training_state)
    (tmp / "config.json").write_text(json.dumps({"checkpoint_format": CHECKPOINT_FORMAT, **config},
                                                indent=2))
    atomic.replace_dir(tmp, directory)


def resolve_checkpoint(path: str | Path) -> Path:
    """A checkpoint directory, or a run directory whose `checkpoints/latest` is used."""
    path = Path(path)
    for candidate in (path, path / "checkpoints" / "latest", path / "latest"):
        if (candidate / "config.json").exists():
            return candidate
    if not path.exists():
        raise SefaInputError("no such checkpoint", file=str(path))
    raise SefaInputError("not a checkpoint (no config.json here or in checkpoints/latest)",
                         file=str(path))
