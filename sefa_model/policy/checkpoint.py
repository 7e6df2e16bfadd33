"""Checkpoints without pickle: safetensors for tensors, JSON for everything else.

    <dir>/config.json             the fully resolved TrainConfig + the flow convention + kind
    <dir>/model.safetensors       raw weights
    <dir>/ema.safetensors         EMA weights (used for evaluation)
    <dir>/normalizer.safetensors  + normalizer.json
    <dir>/processor.json          the observation/action transform (sefa_model/policy/processor.py)
    <dir>/training_state/         optimizer, scheduler, step (only what `--resume` needs)
        state.safetensors, state.json
    <dir>/checksums.json          size and SHA-256 of every other file, written last

A checkpoint directory is written under a temporary name and renamed into place, so a crash
never leaves one that looks complete. The store's integrity rules apply to weights: nothing
non-finite is written, and `open_checkpoint` checks config.json and every checksum before
anything reads the weights (a flipped bit is a clear error, never NaN actions on a robot).
Checkpoints written before checksums.json existed still load; their weights are checked for
finiteness as every checkpoint's are.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any, Collection

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file

from sefa_data.errors import NonFiniteError, SefaInputError
from sefa_data import atomic
from sefa_data.store.integrity import hash_file
from sefa_model.policy.processor import PROCESSOR_FILE

CHECKPOINT_FORMAT = 1
CHECKSUMS_FILE = "checksums.json"
# Written beside a checkpoint after it, tied to its weights by checkpoint_digest rather than
# recorded in its checksums (the execution chosen for it): a checkpoint with one is still
# the checkpoint it was, to load, resume and verify.
EXECUTION_FILE = "execution.json"  # its format: sefa_model/policy/execution.py's save_choice
SIDECAR_FILES = frozenset({EXECUTION_FILE})
# what `kind` in config.json may say: the policies sefa trains (sefa_model/train/batches.py,
# sefa_model/data/couplings.py)
# one_step: a student distilled from the base flow on fresh noise (no couplings: mean flow,
# shortcut); sefa_one_step / reflow_one_step: a student of aligned / unaligned couplings
KINDS = ("base_flow", "ddpm", "reflow", "sefa_one_step", "reflow_one_step", "one_step")
# the sections every checkpoint has written since the first format: without one, the config
# would silently fall back to a default (`objective` and `diffusion` came later and default to
# what those older checkpoints were)
REQUIRED_SECTIONS = ("shape_meta", "policy", "flow", "normalizer", "training")


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


def non_finite(tensors: dict[str, torch.Tensor]) -> tuple[str, int, int] | None:
    """(name, bad values, values) of the first floating tensor with a NaN or Inf, else None."""
    for name, tensor in tensors.items():
        # a sum is NaN or Inf when any element is, and reads the tensor once without a mask
        # the size of the tensor; only then (or on overflow) are the elements checked
        if tensor.is_floating_point() and not bool(torch.isfinite(tensor.sum())):
            bad = int((~torch.isfinite(tensor)).sum())
            if bad:
                return name, bad, tensor.numel()
    return None


def check_finite(tensors: dict[str, torch.Tensor], path: Path | str, what: str) -> None:
    found = non_finite(tensors)
    if found is not None:
        name, bad, total = found
        raise NonFiniteError(f"{what}: {name} has {bad} of {total} values NaN or Inf",
                             file=str(path))


def load_weights(module: torch.nn.Module, path: Path, new_ok: tuple[str, ...] = ()) -> None:
    """Load weights strictly: a checkpoint for another architecture, or weights that are not
    finite, are a clear error. `new_ok`: name prefixes of the module's own parameters that the
    file may lack (a student's new step embedding, which keeps its initialisation)."""
    state = read_tensors(path)
    check_finite(state, path, "non-finite weights (a diverged or damaged checkpoint)")
    own = module.state_dict()
    missing = sorted(k for k in set(own) - set(state) if not (new_ok and k.startswith(new_ok)))
    unexpected = sorted(set(state) - set(own))
    if missing or unexpected:
        what = (f"missing {missing[0]}" if missing else f"unexpected {unexpected[0]}")
        raise SefaInputError(f"weights do not match the model in config.json ({what}; "
                             f"{len(missing)} missing, {len(unexpected)} unexpected)", file=str(path))
    for name, tensor in state.items():
        if tensor.shape != own[name].shape:
            raise SefaInputError(f"weights do not match the model in config.json ({name}: "
                                 f"{tuple(tensor.shape)} vs {tuple(own[name].shape)})", file=str(path))
    module.load_state_dict(state, strict=not new_ok)


def write_checkpoint(directory: Path, *, config: dict, model: torch.nn.Module,
                     ema: torch.nn.Module | None, normalizer, training_state: Any | None,
                     processor: dict | None = None) -> None:
    """Write a whole checkpoint next to `directory`, then swap it into place. Weights that are
    not finite are refused (NonFiniteError) before anything is written."""
    weights = {"model.safetensors": _cpu_state(model)}
    if ema is not None:
        weights["ema.safetensors"] = _cpu_state(ema)
    for name, tensors in weights.items():
        check_finite(tensors, directory / name, "refusing to write non-finite weights")
    tmp = atomic.tmp_name(directory)
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    for name, tensors in weights.items():
        save_file(tensors, str(tmp / name))
    normalizer.save(tmp)
    if processor is not None:
        (tmp / "processor.json").write_text(json.dumps(processor, indent=1))
    if training_state is not None:
        save_state(tmp / "training_state", training_state)
    (tmp / "config.json").write_text(json.dumps({"checkpoint_format": CHECKPOINT_FORMAT, **config},
                                                indent=2))
    write_checksums(tmp)
    atomic.replace_dir(tmp, directory)


def _cpu_state(module: torch.nn.Module) -> dict[str, torch.Tensor]:
    return {k: v.detach().cpu().contiguous() for k, v in module.state_dict().items()}


# ----------------------------------------------------------------------------- integrity


def _files(directory: Path) -> list[str]:
    return sorted(p.relative_to(directory).as_posix() for p in directory.rglob("*")
                  if p.is_file() and p.name != CHECKSUMS_FILE
                  and p.relative_to(directory).as_posix() not in SIDECAR_FILES)


def write_checksums(directory: Path) -> None:
    """Record {relative path: [size, sha256]} of every file of a checkpoint being written."""
    sums = {rel: list(hash_file(directory / rel)) for rel in _files(directory)}
    (directory / CHECKSUMS_FILE).write_text(json.dumps(sums, indent=1))


def checkpoint_digest(directory: Path) -> str | None:
    """One checkpoint's identity: the SHA-256 of its checksums.json, which holds the size and
    SHA-256 of every other file (so no weights are hashed again). What an export records of the
    checkpoint it came from, to tell later whether that is still the stage's current one.
    None for a checkpoint written before checksums existed."""
    import hashlib

    path = directory / CHECKSUMS_FILE
    return hashlib.sha256(path.read_bytes()).hexdigest() if path.exists() else None


def verify_checksums(directory: Path, only: Collection[str] | None = None,
                     what: str = "checkpoint") -> bool:
    """Every recorded file present with its size and SHA-256, and no unrecorded file; with
    `only`, just those files (what a reader is about to read: a deployed policy never reads the
    optimizer state, which is most of a checkpoint's bytes). False for a checkpoint written
    before checksums existed (nothing to check against). `what` names the folder in the
    messages (an export's files are recorded alike)."""
    path = directory / CHECKSUMS_FILE
    if not path.exists():
        return False
    sums = read_json(path)
    if not isinstance(sums, dict):
        raise SefaInputError("corrupt checksums (not a JSON object)", file=str(path))
    for rel, recorded in sums.items():
        if only is not None and rel not in only:
            continue
        file = directory / rel
        if not file.is_file():
            raise SefaInputError(f"missing {what} file (listed in checksums.json): the "
                                 f"{what} is damaged", file=str(file))
        if list(hash_file(file)) != recorded:
            raise SefaInputError("checksum mismatch (the file changed after it was written): "
                                 f"the {what} is damaged", file=str(file))
    on_disk = set(_files(directory)) if only is None else {f for f in only if (directory / f).is_file()}
    extra = sorted(on_disk - set(sums))
    if extra:
        raise SefaInputError("a file not recorded in checksums.json (added or renamed after the "
                             f"{what} was written)", file=str(directory / extra[0]))
    return True


def check_config(meta: Any, path: Path) -> None:
    """config.json must be one this sefa wrote: its format, its kind, its sections."""
    if not isinstance(meta, dict) or "train_config" not in meta:
        raise SefaInputError("config.json has no train_config: not a sefa checkpoint", file=str(path))
    fmt = meta.get("checkpoint_format", CHECKPOINT_FORMAT)
    if not isinstance(fmt, int) or isinstance(fmt, bool) or not 1 <= fmt <= CHECKPOINT_FORMAT:
        raise SefaInputError(f"checkpoint_format {fmt!r} is not one this sefa reads (1.."
                             f"{CHECKPOINT_FORMAT}; a newer sefa wrote it, or it was edited)",
                             file=str(path), key="checkpoint_format")
    kind = meta.get("kind", "base_flow")
    if kind not in KINDS:
        raise SefaInputError(f"unknown kind {kind!r} (one of {', '.join(KINDS)})", file=str(path),
                             key="kind")
    missing = [f for f in REQUIRED_SECTIONS if f not in meta["train_config"]]
    if missing:
        raise SefaInputError(f"train_config lacks '{missing[0]}' (a checkpoint holds its whole "
                             "resolved config: was config.json edited?)", file=str(path),
                             key=f"train_config.{missing[0]}")


def open_checkpoint(path: str | Path) -> tuple[Path, dict]:
    """The checkpoint directory `path` names and its config.json, after every check: all the
    checksums, the config's format, kind and sections. For a run to continue or start from."""
    ckpt = resolve_checkpoint(path)
    verify_checksums(ckpt)
    meta = read_json(ckpt / "config.json")
    check_config(meta, ckpt / "config.json")
    return ckpt, meta


def open_policy(path: str | Path, ema: bool = True) -> tuple[Path, dict, Path]:
    """(directory, config.json, weights file) of a policy to run, after the checks of
    `open_checkpoint` restricted to what running it reads: the optimizer state, most of a
    checkpoint's bytes, is not hashed (bench_integrity.py measures the difference)."""
    ckpt = resolve_checkpoint(path)
    verify_checksums(ckpt, ["config.json"])
    meta = read_json(ckpt / "config.json")
    check_config(meta, ckpt / "config.json")
    weights = weights_file(ckpt, meta, ema)
    verify_checksums(ckpt, [weights.name, "normalizer.json", "normalizer.safetensors",
                            PROCESSOR_FILE])
    return ckpt, meta, weights


def weights_file(ckpt: Path, meta: dict, ema: bool) -> Path:
    """The EMA weights when the run kept an EMA (missing: an error, not a silent fallback to
    the raw weights), else, or when asked with `ema=False`, the raw weights."""
    kept_ema = bool(meta["train_config"].get("training", {}).get("ema", True))
    if ema and kept_ema:
        path = ckpt / "ema.safetensors"
        if not path.exists():
            raise SefaInputError("missing checkpoint file: the run kept EMA weights and they are "
                                 "what evaluation and deployment use (to deploy the raw weights "
                                 "instead: sefa export/serve --raw-weights, or "
                                 "Policy.load(..., ema=False))", file=str(path))
        return path
    return ckpt / "model.safetensors"


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


def saved_progress(ckpt: Path) -> tuple[int, int] | None:
    """(the step a checkpoint was written at, its run's max_steps), from its JSON files alone
    (no tensor is read): how far an interrupted run got, in words. None when unreadable."""
    try:
        tree = json.loads((ckpt / "training_state" / "state.json").read_text())
        step = dict(tree["__dict__"])["step"]
        meta = json.loads((ckpt / "config.json").read_text())
        return int(step), int(meta["train_config"]["training"]["max_steps"])
    except (OSError, ValueError, KeyError, TypeError):
        return None
