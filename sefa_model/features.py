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
and ``meta.json``, replaced whole (`sefa_data.atomic`).

Features are computed in eval mode: center crops, exactly what coupling generation and sampling
see (`window_features`).
"""
from __future__ import annotations

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
from safetensors.torch import load_file, save_file

from sefa_data import atomic
from sefa_data.store_integrity import MANIFEST
from sefa_data.store_journal import fault_point
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


def _load(entry: Path, windows: np.ndarray) -> torch.Tensor | None:
    try:
        tensors = load_file(str(entry / FEATURES_FILE))
    except (OSError, SafetensorError):
        return None  # absent or damaged: recompute (the entry is replaced whole)
    if not np.array_equal(tensors.get("windows", torch.zeros(0)).numpy(), windows):
        return None
    return tensors["features"]


def cached_window_features(model, data, windows: np.ndarray, device: torch.device,
                           cache_dir: Path | None, *, is_main: bool = True,
                           barrier: Callable[[], None] = lambda: None,
                           log: Callable[[str], None] = lambda line: None) -> torch.Tensor:
    """`window_features`, read from `cache_dir` when an entry with the same key exists, else
    computed (by rank 0 alone under torchrun; the other ranks wait and read it) and stored."""
    windows = np.ascontiguousarray(windows, np.int64)
    if cache_dir is None:
        return window_features(model, data, windows, device)
    key = features_key(model, data, windows)
    entry = Path(cache_dir) / key[:16]
    found = _load(entry, windows)
    if found is not None:
        log(f"frozen features: {len(windows)} windows read from {entry}")
        return found
    if is_main:
        started = time.perf_counter()
        features = window_features(model, data, windows, device)
        seconds = time.perf_counter() - started
        tmp = atomic.tmp_name(entry)
        # a writer killed before its rename left a build of this same key: its content is what we
        # are about to write, and the workspace lock keeps out live writers, so it goes
        for stale in entry.parent.glob(f".{entry.name}.tmp-*"):
            shutil.rmtree(stale, ignore_errors=True)
        tmp.mkdir(parents=True)
        save_file({"features": features.contiguous(), "windows": torch.from_numpy(windows)},
                  str(tmp / FEATURES_FILE))
        atomic.write_json(tmp / META_FILE, {"key": key, "windows": int(len(windows)),
                                            "dim": int(features.shape[1]),
                                            "seconds_to_compute": round(seconds, 3)})
        fault_point("features.written")
        atomic.replace_dir(tmp, entry)
        log(f"frozen features: {len(windows)} windows encoded in {seconds:.1f} s, kept in {entry}")
    barrier()
    if not is_main:
        found = _load(entry, windows)
        return found if found is not None else window_features(model, data, windows, device)
    return features
