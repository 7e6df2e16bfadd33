"""The processor: the one transform between what a robot (or the store) gives and what the network
sees, and back. Training, `Policy.predict_action`, the exported artifact and the server's input
checks all use it, as LeRobot's per-policy processor and openpi's Normalize/Unnormalize chain.

    processor = Processor.build(cfg.shape_meta, normalizer)
    obs = processor.obs({"keypoint": kp, "state": st, "image": img})   # model inputs
    chunk = processor.action.unnormalize(x)                            # robot units

Observations, per key of `shape_meta.obs`, (B, To, *frame_shape):
    low-dim   the `dims` slice of the last axis, frames flattened to vectors (B, To, D), then
              normalized (x * scale + offset, `sefa_data.normalizer.affine`)
    rgb       uint8 HWC -> float CHW in [0, 1] (`sefa_data.sampler.image_to_float`); float
              frames are taken as already converted; then, with the key's `resize` [h, w],
              resized bilinearly with antialiasing (torchvision's and LeRobot's Resize) unless
              already of that size
Actions (B, T, Da): normalized for training, unnormalized after sampling.

The parameters are the checkpoint's normalizer, held as buffers so that they trace into an export
and move with `.to(device)`; numpy inputs (a robot's arrays, the store's windows) are computed
with numpy copies of the same float32 values, so no call pays for a tensor round trip. The
processor is defined by the config's `shape_meta` and the normalizer, both saved in every
checkpoint; `describe()` is written beside them as `processor.json` for people and tools, and
checked against what a loaded checkpoint builds.
"""

from __future__ import annotations

from typing import Mapping

import numpy as np
import torch
from torch import nn

from sefa_data.errors import SefaInputError
from sefa_data.normalizer import Normalizer, affine, unaffine
from sefa_data.sampler import image_to_float
from sefa_model.config import ObsSpec, ShapeMeta

PROCESSOR_FILE = "processor.json"


def lowdim_view(key: str, spec: ObsSpec, values):
    """A low-dim key as the policy sees it: the `dims` slice, frames flattened to vectors."""
    if spec.dims is not None:
        values = values[..., spec.dims[0]:spec.dims[1]]
    lead = values.shape[:2] if values.ndim >= 3 else values.shape[:1]
    return values.reshape(*lead, -1)


def buffer_name(key: str) -> str:
    """An observation key as an identifier (buffer and ONNX input names)."""
    return "".join(c if c.isalnum() else "_" for c in key)


class _Affine(nn.Module):
    """One key's normalization parameters: buffers for tensors, numpy copies for arrays."""

    def __init__(self, scale: np.ndarray, offset: np.ndarray):
        super().__init__()
        self.register_buffer("scale", torch.from_numpy(scale.copy()))
        self.register_buffer("offset", torch.from_numpy(offset.copy()))
        self._np = (scale, offset)

    def params_like(self, x):
        """(scale, offset) in x's kind (numpy or torch) and float type; for float32 tensors on
        this module's device the buffers themselves (no per-call work)."""
        if isinstance(x, torch.Tensor):
            scale, offset = self._buffers["scale"], self._buffers["offset"]
            if x.dtype == scale.dtype and x.device == scale.device:
                return scale, offset
            dtype = x.dtype if x.is_floating_point() else torch.float32
            return scale.to(x.device, dtype), offset.to(x.device, dtype)
        if x.dtype == np.float32:
            return self._np
        dtype = x.dtype if x.dtype.kind == "f" else np.float32
        return self._np[0].astype(dtype, copy=False), self._np[1].astype(dtype, copy=False)

    def forward(self, x):
        return affine(x, *self.params_like(x))

    def inverse(self, x):
        return unaffine(x, *self.params_like(x))


class ObsProcessor(nn.Module):
    """Raw observation frames -> the network's inputs (see the module docstring)."""

    def __init__(self, specs: Mapping[str, ObsSpec], normalizer: Normalizer):
        super().__init__()
        self.specs = dict(specs)
        # named by position too: two keys may differ only in characters an identifier lacks
        self.norms = nn.ModuleDict({
            f"{i}_{buffer_name(k)}": _Affine(normalizer.params[k].scale, normalizer.params[k].offset)
            for i, (k, s) in enumerate(self.specs.items()) if s.type == "low_dim"})
        self._norm_of = dict(zip([k for k, s in self.specs.items() if s.type == "low_dim"],
                                 self.norms.values()))  # by store key: predict_action's hot path

    def forward(self, raw: Mapping[str, torch.Tensor | np.ndarray]) -> dict[str, torch.Tensor]:
        return {key: self.one(key, raw[key]) for key in self.specs}

    def one(self, key: str, x):
        """One key's frames (a tensor, or a numpy array for low-dim keys) -> a tensor."""
        spec = self.specs[key]
        if spec.type == "rgb":
            x = image_to_float(x) if x.dtype == torch.uint8 else x
            return resize_images(x, spec.resize) if spec.resize else x
        x = lowdim_view(key, spec, x)
        x = affine(x, *self._norm_of[key].params_like(x))
        return x if torch.is_tensor(x) else torch.from_numpy(np.ascontiguousarray(x))


def resize_images(x: torch.Tensor, size: list[int]) -> torch.Tensor:
    """(..., C, H, W) float frames -> (..., C, h, w), bilinear with antialiasing (what
    torchvision's Resize does to tensors, and LeRobot's resize_shape); frames already of that
    size are returned as they are."""
    h, w = int(size[0]), int(size[1])
    if tuple(x.shape[-2:]) == (h, w):
        return x
    lead = x.shape[:-3]
    flat = x.reshape(-1, *x.shape[-3:])
    out = torch.nn.functional.interpolate(flat, size=(h, w), mode="bilinear",
                                          align_corners=False, antialias=True)
    return out.reshape(*lead, *out.shape[-3:])


class ActionProcessor(nn.Module):
    """Action chunks between robot units and the normalized space the flow lives in."""

    def __init__(self, key: str, normalizer: Normalizer):
        super().__init__()
        self.key = key
        self.norm = _Affine(normalizer.params[key].scale, normalizer.params[key].offset)

    def normalize(self, x):
        return self.norm(x)

    def unnormalize(self, x):
        return self.norm.inverse(x)


class Processor(nn.Module):
    """The observation and the action processor of one policy."""

    def __init__(self, shape_meta: ShapeMeta, normalizer: Normalizer):
        super().__init__()
        missing = [k for k, s in shape_meta.obs.items() if s.type == "low_dim" and k not in normalizer]
        missing += [] if shape_meta.action.key in normalizer else [shape_meta.action.key]
        if missing:
            raise SefaInputError(f"the normalizer has no parameters for '{missing[0]}' (it has: "
                                 f"{', '.join(normalizer.keys)})", key=missing[0])
        self.obs = ObsProcessor(shape_meta.obs, normalizer)
        self.action = ActionProcessor(shape_meta.action.key, normalizer)
        self.shape_meta = shape_meta
        self.normalizer_modes = {k: normalizer.params[k].mode for k in normalizer.keys}

    def inputs(self, n_obs_steps: int) -> dict[str, dict]:
        """What each observation must be when it reaches the processor, without the batch axis:
        the export's inputs and the server's request checks (metadata.json's `obs`)."""
        out = {}
        for key, spec in self.shape_meta.obs.items():
            out[key] = {"type": spec.type, "shape": [n_obs_steps, *spec.frame_shape],
                        "dtype": "uint8" if spec.type == "rgb" else "float32"}
            if spec.type == "low_dim" and spec.dims is not None:
                out[key]["dims"] = list(spec.dims)  # the slice of the last axis the policy reads
        return out

    def describe(self) -> dict:
        """The chain as data (processor.json; the export's and the server's input contract)."""
        obs = {}
        for key, spec in self.shape_meta.obs.items():
            steps = ([{"slice_last_axis": list(spec.dims)}] if spec.dims is not None else [])
            if spec.type == "rgb":
                steps.append({"image": "uint8 HWC -> float32 CHW / 255"})
                if spec.resize:  # only then: older checkpoints' processor.json is unchanged
                    steps.append({"resize": list(spec.resize),
                                  "interpolation": "bilinear, antialiased"})
            else:
                steps += [{"flatten_frame": True},
                          {"normalize": self.normalizer_modes[key], "params": "normalizer.safetensors"}]
            obs[key] = {"type": spec.type, "frame_shape": list(spec.frame_shape or []),
                        "steps": steps}
        key = self.shape_meta.action.key
        return {"sefa_processor": 1, "obs": obs,
                "action": {"key": key, "shape": list(self.shape_meta.action.shape or []),
                           "normalize": self.normalizer_modes[key],
                           "params": "normalizer.safetensors"}}
