"""Per-key affine normalization, x_n = x * scale + offset, fitted on the training split.

The modes are Diffusion Policy's `LinearNormalizer` modes:

* `limits`: [min, max] -> [-1, 1] per element of the frame shape;
* `gaussian`: (x - mean) / std.

A dimension whose range (limits) or std (gaussian) is below `range_eps` is constant in the
data: dividing by its range would blow up noise, so it keeps scale 1 and is only shifted
(limits: to 0; gaussian: by -mean). DP does the same with range_eps = 1e-4.

Parameters are float32 numpy arrays of the key's frame shape. They are saved without pickle:
`normalizer.safetensors` holds the arrays, `normalizer.json` the modes and shapes.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Mapping, TypeVar

import numpy as np
import torch

from sefa_data.errors import SefaInputError
from sefa_data import atomic
from sefa_data.store.zarr_store import EpisodeStore

Mode = Literal["limits", "gaussian"]
MODES = ("limits", "gaussian")
DEFAULT_RANGE_EPS = 1e-4
FORMAT_VERSION = 1
STATE_FILE = "normalizer.safetensors"
CONFIG_FILE = "normalizer.json"

Array = TypeVar("Array", np.ndarray, torch.Tensor)


@dataclass(frozen=True)
class Affine:
    """One key's map: x_n = x * scale + offset, scale and offset of the frame shape."""

    mode: str
    scale: np.ndarray
    offset: np.ndarray

    @property
    def shape(self) -> tuple[int, ...]:
        return tuple(self.scale.shape)


def limits_affine(x: np.ndarray, range_eps: float = DEFAULT_RANGE_EPS) -> Affine:
    """[min, max] -> [-1, 1] over axis 0; constant dimensions -> 0 with scale 1."""
    lo, hi = x.min(axis=0), x.max(axis=0)
    constant = (hi - lo) < range_eps
    scale = np.where(constant, 1.0, 2.0 / np.where(constant, 1.0, hi - lo))
    offset = np.where(constant, -lo, -1.0 - lo * scale)
    return _affine("limits", scale, offset)


def gaussian_affine(x: np.ndarray, range_eps: float = DEFAULT_RANGE_EPS) -> Affine:
    """(x - mean) / std over axis 0; dimensions with std < range_eps are only centred."""
    mean, std = x.mean(axis=0), x.std(axis=0)
    scale = np.where(std < range_eps, 1.0, 1.0 / np.where(std < range_eps, 1.0, std))
    return _affine("gaussian", scale, -mean * scale)


def _affine(mode: str, scale: np.ndarray, offset: np.ndarray) -> Affine:
    return Affine(mode, np.asarray(scale, np.float32), np.asarray(offset, np.float32))


_FITTERS = {"limits": limits_affine, "gaussian": gaussian_affine}


class Normalizer:
    """Affine normalization of named keys; see the module docstring."""

    def __init__(self, params: Mapping[str, Affine], range_eps: float = DEFAULT_RANGE_EPS):
        self.params = dict(params)
        self.range_eps = float(range_eps)
        # torch copies of the parameters per (key, device, dtype), so that a training step
        # does not copy them to the GPU every call
        self._torch: dict[tuple[str, torch.device, torch.dtype], tuple[torch.Tensor, torch.Tensor]] = {}

    @property
    def keys(self) -> list[str]:
        return sorted(self.params)

    def __contains__(self, key: str) -> bool:
        return key in self.params

    # ---- fitting

    @classmethod
    def fit(cls, data: Mapping[str, np.ndarray], modes: Mapping[str, Mode],
            range_eps: float = DEFAULT_RANGE_EPS) -> "Normalizer":
        """Fit each key of `modes` on `data[key]`, shaped (N, *frame_shape): statistics per
        element of the frame shape, over the N frames."""
        params = {}
        for key, mode in modes.items():
            if mode not in _FITTERS:
                raise SefaInputError(f"unknown normalizer mode '{mode}' (use one of "
                                     f"{', '.join(MODES)})", key=key)
            if key not in data:
                raise SefaInputError("no data to fit the normalizer on", key=key)
            x = np.asarray(data[key], dtype=np.float64)
            if x.ndim < 1 or len(x) == 0:
                raise SefaInputError("no frames to fit the normalizer on", key=key)
            if not np.isfinite(x).all():
                raise SefaInputError("NaN or Inf in the data the normalizer is fitted on", key=key)
            params[key] = _FITTERS[mode](x, range_eps)
        return cls(params, range_eps)

    # ---- applying

    def normalize(self, key: str, x: Array) -> Array:
        return affine(x, *self._params_like(key, x))

    def unnormalize(self, key: str, x: Array) -> Array:
        return unaffine(x, *self._params_like(key, x))

    def _params_like(self, key: str, x: Array):
        """This key's scale and offset as numpy or torch, on x's device and in x's float type."""
        if key not in self.params:
            raise SefaInputError(f"the normalizer has no such key (it has: "
                                 f"{', '.join(self.keys)})", key=key)
        p = self.params[key]
        tail = tuple(x.shape[x.ndim - len(p.shape):]) if x.ndim >= len(p.shape) else None
        if tail != p.shape:
            raise SefaInputError(f"array of shape {tuple(x.shape)} does not end in the "
                                 f"normalizer's frame shape {p.shape}", key=key)
        if isinstance(x, torch.Tensor):
            dtype = x.dtype if x.is_floating_point() else torch.float32
            cache_key = (key, x.device, dtype)
            if cache_key not in self._torch:
                self._torch[cache_key] = tuple(torch.from_numpy(a).to(x.device, dtype)
                                               for a in (p.scale, p.offset))
            return self._torch[cache_key]
        dtype = x.dtype if np.issubdtype(x.dtype, np.floating) else np.float32
        return p.scale.astype(dtype, copy=False), p.offset.astype(dtype, copy=False)

    def digest(self) -> str:
        """sha256 of the modes and parameters: names the space normalized arrays live in."""
        import hashlib

        h = hashlib.sha256(json.dumps(self.to_config(), sort_keys=True).encode())
        for name, a in sorted(self.state_dict().items()):
            h.update(name.encode() + np.ascontiguousarray(a, np.float32).tobytes())
        return h.hexdigest()

    # ---- serialization

    def state_dict(self) -> dict[str, np.ndarray]:
        out = {}
        for key, p in self.params.items():
            out[f"{key}.scale"], out[f"{key}.offset"] = p.scale, p.offset
        return out

    def to_config(self) -> dict:
        return {"sefa_normalizer": FORMAT_VERSION, "range_eps": self.range_eps,
                "keys": {k: {"mode": p.mode, "shape": list(p.shape)}
                         for k, p in sorted(self.params.items())}}

    @classmethod
    def from_state(cls, state: Mapping[str, np.ndarray], config: Mapping,
                   state_file: str | None = None, config_file: str | None = None) -> "Normalizer":
        """Rebuild from `state_dict()` and `to_config()`; the file names go into errors."""
        keys = config.get("keys")
        if (config.get("sefa_normalizer") != FORMAT_VERSION or not isinstance(keys, dict)
                or not all(isinstance(e, dict) and e.get("mode") in MODES
                           and isinstance(e.get("shape"), list) for e in keys.values())):
            raise SefaInputError(f"not a sefa normalizer config of format {FORMAT_VERSION} "
                                 f"(keys: {{name: {{mode: {'|'.join(MODES)}, shape: [...]}}}})",
                                 file=config_file)
        expected = {f"{k}.{part}" for k in keys for part in ("scale", "offset")}
        if set(state) != expected:
            odd = sorted(set(state) ^ expected)
            raise SefaInputError(f"the arrays do not match the keys of {CONFIG_FILE} "
                                 f"({', '.join(odd[:4])})", file=state_file)
        params = {}
        for key, entry in keys.items():
            shape = tuple(entry["shape"])
            scale = np.asarray(state[f"{key}.scale"], np.float32)
            offset = np.asarray(state[f"{key}.offset"], np.float32)
            if scale.shape != shape or offset.shape != shape:
                raise SefaInputError(f"scale {scale.shape} and offset {offset.shape} where "
                                     f"{CONFIG_FILE} says {shape}", file=state_file, key=key)
            if not (np.isfinite(scale).all() and np.isfinite(offset).all() and (scale != 0).all()):
                raise SefaInputError("non-finite or zero normalizer parameters",
                                     file=state_file, key=key)
            params[key] = Affine(entry["mode"], scale, offset)
        return cls(params, config.get("range_eps", DEFAULT_RANGE_EPS))

    def save(self, directory: str | Path) -> None:
        """Write normalizer.safetensors and normalizer.json into `directory`; each file is
        replaced whole, so a crash never leaves half a file."""
        from safetensors.numpy import save_file

        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        with atomic.writing(directory / STATE_FILE) as tmp:
            save_file({k: np.ascontiguousarray(v) for k, v in self.state_dict().items()}, str(tmp))
        atomic.write_text(directory / CONFIG_FILE, json.dumps(self.to_config(), indent=1))

    @classmethod
    def load(cls, directory: str | Path) -> "Normalizer":
        from safetensors.numpy import load_file

        state_path, config_path = Path(directory) / STATE_FILE, Path(directory) / CONFIG_FILE
        for path in (state_path, config_path):
            if not path.is_file():
                raise SefaInputError("no such file (a normalizer is saved as "
                                     f"{STATE_FILE} + {CONFIG_FILE})", file=str(path))
        try:
            config = json.loads(config_path.read_text())
        except (ValueError, UnicodeDecodeError) as e:
            raise SefaInputError(f"not valid JSON ({e})", file=str(config_path)) from None
        try:
            state = load_file(str(state_path))
        except Exception as e:  # safetensors raises its own error types for corrupt headers
            raise SefaInputError(f"not a readable safetensors file ({e})",
                                 file=str(state_path)) from None
        if not isinstance(config, dict):
            config = {}  # from_state reports it as not a normalizer config
        return cls.from_state(state, config, str(state_path), str(config_path))


def affine(x: Array, scale: Array, offset: Array) -> Array:
    """x_n = x * scale + offset: the one place the normalization is written (the normalizer, the
    policy's processor and the exported artifact all call it)."""
    return _as_float(x) * scale + offset


def unaffine(x: Array, scale: Array, offset: Array) -> Array:
    """The inverse of `affine`."""
    return (_as_float(x) - offset) / scale


def _as_float(x: Array) -> Array:
    if isinstance(x, torch.Tensor):
        return x if x.is_floating_point() else x.float()
    return x if x.dtype.kind == "f" else x.astype(np.float32)  # kind "f": numpy's floating types


def train_frames(store: EpisodeStore, key: str, split: str = "train") -> np.ndarray:
    """Every frame of `key` in the split's episodes, (n, *frame_shape)."""
    in_split = np.repeat(store.mask(split).astype(bool), store.episode_lengths)
    return store.root["data"][key][:][in_split]
