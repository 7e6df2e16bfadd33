"""A sefa policy as a LeRobot policy folder: what `sefa export --format lerobot` writes
(sefa_deploy/lerobot_export.py) and what the `lerobot_policy_sefa` plugin
(integrations/lerobot) loads. This module owns the folder's layout, so the writer and the
reader cannot drift apart, and it imports neither LeRobot nor sefa's simulators.

    DIR/config.json                 LeRobot's policy config, `"type": "sefa"`: LeRobot's own
                                    fields (input_features and output_features in LeRobot's
                                    names, n_obs_steps, device, ...), the execution settings
                                    (execution, replan_every, ensemble_k), the sampler (solver,
                                    steps), and `sefa`: the training config, the normalizer's
                                    modes and shapes, the input map, the checkpoint it came from
    DIR/model.safetensors           the network (`model.<name>`, the EMA weights) and the
                                    normalizer (`normalizer.<store key>.scale|offset`)
    DIR/policy_preprocessor.json    LeRobot's standard steps: rename, batch, device
    DIR/policy_postprocessor.json   the device step (to the CPU)

The normalization is inside the policy, not in LeRobot's normalizer steps: sefa's processor (the
`dims` slice, frames flattened, x * scale + offset in float32) is the transform the policy was
trained with, and LeRobot's MIN_MAX and MEAN_STD steps compute it another way (with their own
eps), so actions would match sefa's only approximately; kept with the weights, the normalizer
also cannot be swapped for another dataset's. The pre- and postprocessor therefore hold only
LeRobot's standard rename, batch and device steps, which LeRobot's tools override by name.

The input map ties each LeRobot observation feature to the store key the policy reads:
`observation.state` -> `state`, `observation.environment_state` -> `keypoint`, ... A feature may
reach its key through `points`, a (K, S) matrix of affine weights: the feature holds S points of
a rigid body, the key K points of the same body, and key = points @ feature (gym-pusht's 8 T
corners -> the training store's 9 keypoints; sefa_sim.pusht.affine_weights). A low-dim key read
through a `dims` slice takes either its whole frame or the slice alone.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping

import numpy as np
import torch
from torch import nn

from sefa_data.errors import SefaInputError
from sefa_data.normalizer import Normalizer
from sefa_model.config import ObsSpec, TrainConfig, saved_train_config
from sefa_model.distributed import cpu_noise
from sefa_model.policy.checkpoint import check_finite, read_tensors
from sefa_model.policy.model import FlowPolicyModel
from sefa_model.policy.processor import Processor

POLICY_TYPE = "sefa"  # LeRobot's `--policy.type`, the config's "type"
FORMAT = 1  # config.json's sefa.format
CONFIG_FILE = "config.json"
WEIGHTS_FILE = "model.safetensors"
PREPROCESSOR_FILE = "policy_preprocessor.json"
POSTPROCESSOR_FILE = "policy_postprocessor.json"
FILES = (CONFIG_FILE, WEIGHTS_FILE, PREPROCESSOR_FILE, POSTPROCESSOR_FILE)
ACTION = "action"  # LeRobot's one action feature
ENV_STATE = "observation.environment_state"
STATE = "observation.state"
# LeRobot's image names: one camera `observation.image`, several `observation.images.<name>`
IMAGE_NAME = re.compile(r"^observation\.(image|images\.[^.\s]+)$")


def check_files(folder: str | Path) -> None:
    """One line naming the first file a folder lacks, before LeRobot reads any of them."""
    for name in FILES:
        if not (Path(folder) / name).is_file():
            raise SefaInputError(f"missing: a sefa policy folder holds {', '.join(FILES)}; "
                                 "export it again (sefa export CHECKPOINT --format lerobot "
                                 "--out DIR)", file=str(Path(folder) / name))


def check_section(section: Mapping, source: str = CONFIG_FILE) -> None:
    """config.json's `sefa` section is one this sefa reads."""
    if not isinstance(section, Mapping) or section.get("format") != FORMAT:
        found = section.get("format") if isinstance(section, Mapping) else None
        raise SefaInputError(f"sefa.format is {found!r}; this sefa reads format {FORMAT} (export "
                             "the policy again with this sefa, or install the sefa that wrote it)",
                             file=source)


@dataclass(frozen=True)
class InputMap:
    """One LeRobot observation feature and the store key it feeds (see the module docstring)."""

    feature: str  # LeRobot's name, e.g. observation.state
    key: str  # the store's key, e.g. state
    points: list[list[float]] | None = None  # (K, S): key's K points from the feature's S points

    def to_json(self) -> dict:
        return {"feature": self.feature, "key": self.key, "points": self.points}


def feature_type(name: str) -> str:
    """LeRobot's FeatureType of an observation name."""
    if IMAGE_NAME.match(name):
        return "VISUAL"
    return "ENV" if name == ENV_STATE else "STATE"


def default_name(key: str, spec: ObsSpec, n_cameras: int) -> str | None:
    """LeRobot's name for a store key, or None when there is no obvious one: LeRobot's own
    names stay; `state` and `agent_pos` are the robot state, `keypoint` the environment state,
    a camera `observation.image` (the only one) or `observation.images.<key>`."""
    if key.startswith("observation."):
        return key
    if spec.type == "rgb":
        return "observation.image" if n_cameras == 1 else f"observation.images.{key}"
    return {"state": STATE, "agent_pos": STATE, "keypoint": ENV_STATE}.get(key)


def input_map(cfg: TrainConfig, names: Mapping[str, str] | None = None,
              points: Mapping[str, np.ndarray] | None = None) -> list[InputMap]:
    """The policy's observation keys, in order, each with its LeRobot feature: `names` (store
    key -> LeRobot name, e.g. from `--key-map observation.state=state`) first, else
    `default_name`. `points`: store key -> its (K, S) affine weights. One line naming the key
    when a key has no LeRobot name or two keys would share one."""
    names, points = dict(names or {}), dict(points or {})
    obs = cfg.shape_meta.obs
    stray = [k for k in [*names, *points] if k not in obs]
    if stray:
        raise SefaInputError(f"the policy reads no observation '{stray[0]}' (it reads: "
                             f"{', '.join(obs)})", key="--key-map")
    n_cameras = sum(spec.type == "rgb" for spec in obs.values())
    out, seen = [], {}
    for key, spec in obs.items():
        name = names.get(key) or default_name(key, spec, n_cameras)
        if name is None:
            raise SefaInputError(
                f"LeRobot has no name for the policy's observation '{key}' ({spec.type}, frame "
                f"{spec.frame_shape}): name it with --key-map observation.NAME={key} (LeRobot "
                "passes observation.state, observation.environment_state, observation.image "
                "and observation.images.<camera>)", key="--key-map")
        check_name(name, key, spec)
        if name in seen:
            raise SefaInputError(f"'{seen[name]}' and '{key}' would both be LeRobot's '{name}'; "
                                 "map one elsewhere with --key-map", key="--key-map")
        seen[name] = key
        w = points.get(key)
        out.append(InputMap(name, key, None if w is None else np.asarray(w, float).tolist()))
    return out


def check_name(name: str, key: str, spec: ObsSpec) -> None:
    if not name.startswith("observation.") or name == "observation.":
        raise SefaInputError(f"'{name}' for '{key}': LeRobot's observation names start with "
                             "'observation.'", key="--key-map")
    if (spec.type == "rgb") != (feature_type(name) == "VISUAL"):
        want = "an image name (observation.image or observation.images.<camera>)" \
            if spec.type == "rgb" else "a name that is not an image's"
        raise SefaInputError(f"'{key}' is {'a camera' if spec.type == 'rgb' else 'low-dim'}: "
                             f"LeRobot needs {want}, not '{name}'", key="--key-map")


def feature_shape(spec: ObsSpec, entry: InputMap) -> list[int]:
    """What LeRobot hands over for this feature, without the batch axis: images CHW, a low-dim
    key as the flat vector it feeds (the `dims` slice alone, if the key has one), a key reached
    through points the S points flattened."""
    if spec.type == "rgb":
        h, w, c = spec.frame_shape
        return [c, h, w]
    if entry.points is not None:
        return [2 * len(entry.points[0])]
    return [lowdim_width(spec, sliced=spec.dims is not None)]


def lowdim_width(spec: ObsSpec, sliced: bool) -> int:
    frame = list(spec.frame_shape)
    if sliced:
        frame[-1] = spec.dims[1] - spec.dims[0]
    return math.prod(frame)


class ChunkModel(nn.Module):
    """The policy behind a LeRobot folder: LeRobot-named observation histories in, action chunks
    in robot units out. `load` fills it from model.safetensors; until then it has no
    normalizer and predicts nothing."""

    def __init__(self, section: Mapping, solver: str | None, steps: int | None,
                 source: str = CONFIG_FILE):
        super().__init__()
        check_section(section, source)
        self.cfg = saved_train_config(section["train_config"], source=source)
        self.inputs = [InputMap(**e) for e in section["inputs"]]
        self.normalizer_config = dict(section["normalizer"])
        self.solver, self.steps = solver, steps
        self.model = FlowPolicyModel(self.cfg)
        self.normalizer: Normalizer | None = None
        self.processor: Processor | None = None
        self._points = {m.feature: torch.tensor(m.points, dtype=torch.float32)
                        for m in self.inputs if m.points is not None}
        self.eval()  # inference only: an image encoder center-crops (training crops at random)

    # ---- weights

    def set_normalizer(self, normalizer: Normalizer) -> None:
        self.normalizer = normalizer
        device = next(self.model.parameters()).device
        self.processor = Processor(self.cfg.shape_meta, normalizer).to(device)

    def state_tensors(self) -> dict[str, torch.Tensor]:
        """model.safetensors' tensors: the network's and the normalizer's."""
        if self.normalizer is None:
            raise RuntimeError("ChunkModel.load was not called: the model has no weights")
        out = {f"model.{k}": v.detach().cpu().contiguous() for k, v in self.model.state_dict().items()}
        for name, a in self.normalizer.state_dict().items():
            out[f"normalizer.{name}"] = torch.from_numpy(np.ascontiguousarray(a))
        return out

    def load(self, path: str | Path) -> "ChunkModel":
        """Fill the network and the normalizer from `path` (model.safetensors): every tensor
        present, none extra, all finite, or one line naming the file."""
        tensors = read_tensors(Path(path))
        check_finite(tensors, path, "non-finite weights")
        weights = {k[len("model."):]: v for k, v in tensors.items() if k.startswith("model.")}
        stats = {k[len("normalizer."):]: v.numpy() for k, v in tensors.items()
                 if k.startswith("normalizer.")}
        other = sorted(set(tensors) - {f"model.{k}" for k in weights}
                       - {f"normalizer.{k}" for k in stats})
        if other:
            raise SefaInputError(f"unexpected tensor {other[0]} (a sefa LeRobot export holds "
                                 "model.* and normalizer.*)", file=str(path))
        normalizer = Normalizer.from_state(stats, self.normalizer_config, str(path), CONFIG_FILE)
        own = self.model.state_dict()
        missing, extra = sorted(set(own) - set(weights)), sorted(set(weights) - set(own))
        if missing or extra:
            what = f"missing model.{missing[0]}" if missing else f"unexpected model.{extra[0]}"
            raise SefaInputError(f"the weights do not match the network in {CONFIG_FILE} "
                                 f"({what})", file=str(path))
        bad = [k for k in own if own[k].shape != weights[k].shape]
        if bad:
            raise SefaInputError(f"the weights do not match the network in {CONFIG_FILE} "
                                 f"(model.{bad[0]}: {tuple(weights[bad[0]].shape)} vs "
                                 f"{tuple(own[bad[0]].shape)})", file=str(path))
        self.model.load_state_dict(weights)
        self.set_normalizer(normalizer)
        return self

    # ---- prediction

    @property
    def n_obs_steps(self) -> int:
        return self.cfg.policy.n_obs_steps

    def store_frames(self, frames: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """LeRobot name -> (B, To, *feature shape) into store key -> (B, To, *frame) as the
        processor takes them (images stay CHW floats in [0, 1], as LeRobot hands them over)."""
        out = {}
        for m in self.inputs:
            if m.feature not in frames:
                raise SefaInputError(f"the observation has no '{m.feature}' (the policy reads: "
                                     f"{', '.join(i.feature for i in self.inputs)})", key=m.feature)
            spec = self.cfg.shape_meta.obs[m.key]
            x = frames[m.feature]
            out[m.key] = x if spec.type == "rgb" else self._lowdim(m, spec, x.float())
        return out

    def _lowdim(self, m: InputMap, spec: ObsSpec, x: torch.Tensor) -> torch.Tensor:
        lead = x.shape[:2]
        if m.feature in self._points:
            w = self._points[m.feature].to(x.device)
            pts = x.reshape(*lead, w.shape[1], 2)
            return torch.einsum("ks,btsd->btkd", w, pts)
        width = x[0, 0].numel()
        if width == lowdim_width(spec, sliced=False):
            return x.reshape(*lead, *spec.frame_shape)
        if spec.dims is not None and len(spec.frame_shape) == 1 and width == lowdim_width(spec, True):
            # the slice alone: placed where the processor's `dims` slice reads it
            a, b = spec.dims
            return nn.functional.pad(x.reshape(*lead, -1), (a, spec.frame_shape[0] - b))
        allowed = sorted({lowdim_width(spec, False)}
                         | ({lowdim_width(spec, True)} if spec.dims is not None else set()))
        raise SefaInputError(f"'{m.feature}' has {width} values a frame; the policy reads "
                             f"{' or '.join(map(str, allowed))} (store key '{m.key}')", key=m.feature)

    def forward(self, frames: Mapping[str, torch.Tensor], noise: torch.Tensor) -> torch.Tensor:
        """frames: LeRobot name -> (B, To, *feature shape); noise (B, horizon, Da) standard
        normal -> the whole chunk (B, horizon, Da) in robot units. B = 1 frames with noise of
        batch N: N chunks of the one observation, encoded once."""
        if self.processor is None:
            raise RuntimeError("ChunkModel.load was not called: the model has no weights")
        obs = self.processor.obs(self.store_frames(frames))
        x = self.model.sample(self.model.encode(obs, samples=noise.shape[0]), noise,
                              solver=self.solver, steps=self.steps).x
        return self.processor.action.unnormalize(x)

    def noise(self, batch: int, device: torch.device,
              generator: torch.Generator | None = None) -> torch.Tensor:
        """Standard normal noise for `batch` chunks, drawn on the CPU (the same values on every
        device, as `Policy.predict_action` draws it)."""
        p = self.cfg.policy
        return cpu_noise((batch, p.horizon, self.cfg.shape_meta.action.shape[-1]), generator, device)
