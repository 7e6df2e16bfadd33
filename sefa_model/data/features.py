"""Frozen observation features: the base encoder's condition of every training window, computed
once and kept as an artifact, so that reflow, alignment and distillation do not run the CNN again.

With `training.freeze_encoder` (the coupling stages' default) the reflowed flows and the student
keep the base policy's encoder, so the condition of a window never changes after `sefa train`.
The file is keyed by everything the condition depends on:

- the encoder's weights and the normalizer's statistics (low-dim keys are normalized before
  they join the condition),
- the store's content (its checksum manifest, which `verify="full"` has just checked),
- the window definition (horizon, observation steps and specs) and the list of windows,

so a key names one array, and a changed encoder or store simply misses. A cache entry is a
folder ``<key>/`` with ``features.safetensors`` ({"features": (N, D) float32, "windows": (N,)})
and ``meta.json`` (the key, N, D and the sha256 of the safetensors file), replaced whole
(`sefa_data.atomic`).

An entry is checked whole every time it is read: its checksum, both tensors, their shapes (N
windows, the encoder's width), the windows themselves and finite values. A damaged entry is
never used: the command stops with one line naming the file and what is wrong, and the same
command with `--force` (`rebuilding_damaged`) encodes the windows again and replaces it. An
entry written before checksums (no sha256 in meta.json) is encoded again, with a line saying so.
Non-finite features are never written: the encoder that gave them is reported instead.

Features are computed in eval mode: center crops, exactly what coupling generation and sampling
see (`window_features`).
"""
from __future__ import annotations

import contextlib
import contextvars
import hashlib
import json
import shutil
import time
from dataclasses import asdict
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from safetensors import SafetensorError
from safetensors.torch import load as load_bytes, save_file

from sefa_data import atomic
from sefa_data.errors import SefaInputError
from sefa_data.store.integrity import MANIFEST
from sefa_data.store.journal import fault_point
from sefa_model.progress import report

FEATURES_FILE = "features.safetensors"
META_FILE = "meta.json"


@torch.no_grad()
def window_features(model, data, windows: np.ndarray, device: torch.device,
                    batch: int = 512) -> torch.Tensor:
    """(len(windows), D) float32 on the host: the condition `model.encode` gives each training
    window in eval mode (center crops), exactly what coupling generation and sampling see."""
    was_training = model.training
    model.eval()
    out = []
    report("features", 0, len(windows))  # the bar from the first second, not after a batch
    for b in range(0, len(windows), batch):
        obs, _ = data.tensors(data.train, windows[b:b + batch], device)
        out.append(model.encode(obs).float().cpu())
        # an image encoder over every training window takes minutes on a CPU: show it
        report("features", min(b + batch, len(windows)), len(windows))
    model.train(was_training)
    return torch.cat(out) if out else torch.zeros(0, model.obs_encoder.out_dim)


def _tensor_digest(digest, tensors: dict[str, torch.Tensor]) -> None:
    for name in sorted(tensors):
        t = tensors[name].detach().cpu().contiguous()
        digest.update(f"{name}:{t.dtype}:{tuple(t.shape)}\n".encode())
        digest.update(t.view(torch.uint8).numpy().tobytes() if t.numel() else b"")


def features_key(model, data, windows: np.ndarray) -> str:
    """sha256 over what a window's frozen condition depends on (see the module docstring)."""
    digest = hashlib.sha256(b"sefa-features-1\n")
    _tensor_digest(digest, dict(model.obs_encoder.state_dict()))
    _tensor_digest(digest, {k: torch.as_tensor(np.asarray(v)) for k, v in
                            data.normalizer.state_dict().items()})
    manifest = Path(data.store.path) / MANIFEST
    digest.update(manifest.read_bytes() if manifest.exists() else str(data.store.path).encode())
    cfg = data.cfg
    digest.update(json.dumps({"obs": {k: asdict(v) for k, v in cfg.shape_meta.obs.items()},
                              "horizon": cfg.policy.horizon, "n_obs_steps": cfg.policy.n_obs_steps,
                              "n_train_windows": len(data.train)}, sort_keys=True).encode())
    digest.update(np.ascontiguousarray(windows, np.int64).tobytes())
    return digest.hexdigest()


# The command's --force: it rebuilds a damaged entry instead of stopping (set by the CLI around
# the stages it runs; a context variable, so that the training code in between needs no flag).
_REBUILD_DAMAGED: contextvars.ContextVar[bool] = contextvars.ContextVar("sefa_features_rebuild",
                                                                         default=False)


@contextlib.contextmanager
def rebuilding_damaged(on: bool = True):
    """Within the block a damaged cache entry is encoded again instead of being an error."""
    token = _REBUILD_DAMAGED.set(on)
    try:
        yield
    finally:
        _REBUILD_DAMAGED.reset(token)


class _Damaged(Exception):
    def __init__(self, file: Path, what: str):
        super().__init__(what)
        self.file, self.what = file, what


class _Unchecked(Exception):
    """An entry written before checksums: not damaged, but not to be trusted either."""


def _load(entry: Path, key: str, windows: np.ndarray, dim: int) -> torch.Tensor | None:
    """The entry's features, checked whole; None when there is no entry. Raises `_Damaged`
    (or `_Unchecked`) instead of returning anything it could not check."""
    meta_file, data_file = entry / META_FILE, entry / FEATURES_FILE
    if not entry.exists():
        return None
    try:
        meta = json.loads(meta_file.read_text())
    except FileNotFoundError:
        raise _Damaged(meta_file, "missing") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise _Damaged(meta_file, f"unreadable ({' '.join(str(e).split())[:120]})") from None
    if not isinstance(meta, dict):
        raise _Damaged(meta_file, "not a JSON object")
    if "sha256" not in meta:
        raise _Unchecked()
    if meta.get("key") != key:
        raise _Damaged(meta_file, "written for another key than its folder's")
    try:
        raw = data_file.read_bytes()
    except FileNotFoundError:
        raise _Damaged(data_file, "missing") from None
    if hashlib.sha256(raw).hexdigest() != meta["sha256"]:
        raise _Damaged(data_file, "its sha256 differs from the one meta.json recorded when it was "
                                  "written (the file changed or was damaged since)")
    try:
        tensors = load_bytes(raw)
    except (SafetensorError, ValueError, OSError) as e:
        text = " ".join(str(e).split())[:120]
        raise _Damaged(data_file, f"not a readable safetensors file ({text})") from None
    for name in ("features", "windows"):
        if name not in tensors:
            held = ", ".join(sorted(tensors)) or "none"
            raise _Damaged(data_file, f"no '{name}' tensor (it holds {held})")
    features, stored = tensors["features"], tensors["windows"]
    expected = (len(windows), dim)
    if features.dtype != torch.float32 or tuple(features.shape) != expected:
        raise _Damaged(data_file, f"'features' is {features.dtype} {tuple(features.shape)}, "
                                  f"expected torch.float32 {expected} ({len(windows)} windows, "
                                  f"the encoder's width {dim})")
    if stored.shape != (len(windows),) or not np.array_equal(stored.numpy(), windows):
        raise _Damaged(data_file, f"'windows' {tuple(stored.shape)} are not the "
                                  f"{len(windows)} windows of its key")
    bad = _nonfinite_rows(features)
    if len(bad):
        raise _Damaged(data_file, f"'features' hold NaN or inf in {len(bad)} of {len(windows)} "
                                  f"windows (the first: window {int(windows[bad[0]])})")
    return features


def _nonfinite_rows(features: torch.Tensor) -> np.ndarray:
    return np.flatnonzero(~torch.isfinite(features).reshape(len(features), -1).all(dim=1).numpy())


def _checked(entry: Path, key: str, windows: np.ndarray, dim: int,
             log: Callable[[str], None]) -> torch.Tensor | None:
    """`_load`, with what to do about an entry that cannot be used: an error naming it, or
    (under `rebuilding_damaged`, and for an entry without a checksum) None, a miss."""
    try:
        return _load(entry, key, windows, dim)
    except _Unchecked:
        log(f"frozen features: {entry} was written without a checksum (an older sefa): "
            "encoding again")
        return None
    except _Damaged as e:
        if _REBUILD_DAMAGED.get():
            log(f"frozen features: {e.file}: damaged ({e.what}): encoding again (--force)")
            return None
        raise SefaInputError(f"damaged features cache entry, not used: {e.what}; the same command "
                             "with --force encodes the windows again and replaces it",
                             file=str(e.file)) from None


def cached_window_features(model, data, windows: np.ndarray, device: torch.device,
                           cache_dir: Path | None, *, is_main: bool = True,
                           barrier: Callable[[], None] = lambda: None,
                           log: Callable[[str], None] = lambda line: None) -> torch.Tensor:
    """`window_features`, read from `cache_dir` when an entry with the same key exists, else
    computed (by rank 0 alone under torchrun; the other ranks wait and read it) and stored."""
    windows = np.ascontiguousarray(windows, np.int64)
    if cache_dir is None:
        return _finite(window_features(model, data, windows, device), windows)
    key = features_key(model, data, windows)
    entry = Path(cache_dir) / key[:16]
    dim = int(model.obs_encoder.out_dim)
    found = _checked(entry, key, windows, dim, log)
    if found is not None:
        log(f"frozen features: {len(windows)} windows read from {entry}")
        return found
    if is_main:
        started = time.perf_counter()
        features = _finite(window_features(model, data, windows, device), windows)
        seconds = time.perf_counter() - started
        tmp = atomic.tmp_name(entry)
        # a writer killed before its rename left a build of this same key: its content is what we
        # are about to write, and the workspace lock keeps out live writers, so it goes
        for stale in entry.parent.glob(f".{entry.name}.tmp-*"):
            shutil.rmtree(stale, ignore_errors=True)
        tmp.mkdir(parents=True)
        save_file({"features": features.contiguous(), "windows": torch.from_numpy(windows)},
                  str(tmp / FEATURES_FILE))
        # the checksum of the bytes as written, read back: what a reader must find
        sha256 = hashlib.sha256((tmp / FEATURES_FILE).read_bytes()).hexdigest()
        atomic.write_json(tmp / META_FILE, {"key": key, "windows": int(len(windows)),
                                            "dim": int(features.shape[1]), "sha256": sha256,
                                            "seconds_to_compute": round(seconds, 3)})
        fault_point("features.written")
        atomic.replace_dir(tmp, entry)
        log(f"frozen features: {len(windows)} windows encoded in {seconds:.1f} s, kept in {entry}")
    barrier()
    if not is_main:
        found = _checked(entry, key, windows, dim, log)
        if found is None:
            found = _finite(window_features(model, data, windows, device), windows)
        return found
    return features


def _finite(features: torch.Tensor, windows: np.ndarray) -> torch.Tensor:
    """Non-finite features would train a NaN policy: they are refused, never cached or used."""
    bad = _nonfinite_rows(features)
    if len(bad):
        raise SefaInputError(f"the frozen encoder gives NaN or inf features for {len(bad)} of "
                             f"{len(windows)} training windows (the first: window "
                             f"{int(windows[bad[0]])}): the policy it comes from has non-finite "
                             "weights or the store non-finite observations; nothing was cached",
                             key="frozen features")
    return features
