"""What `sefa serve` runs: a checkpoint through `Policy.predict_action`, or an export through
onnxruntime or TorchScript, behind one call.

    backend = load_backend("distill")            # or an export directory
    action, action_pred = backend(obs, noise)    # numpy in, numpy out (generator=: the
                                                 # checkpoint's diffusion sampler's later noises)

`obs` holds per key (B, To, *frame_shape) arrays already checked against `backend.metadata`
(low-dim float32 in the store's units, images uint8 HWC) and `noise` (B, horizon, Da) float32;
both outputs are float32 in action units. Every backend has the same metadata, the export's
`metadata.json`, so that a client cannot tell them apart except by speed.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import torch

from sefa_data.errors import SefaInputError
from sefa_deploy.metadata import METADATA_FILE, build_metadata, find_fps, open_export


class CheckpointBackend:
    """A checkpoint in-process: any solver the checkpoint takes, adaptive ones included."""

    name = "checkpoint"

    def __init__(self, path: str | Path, *, device: str = "cpu", solver: str | None = None,
                 steps: int | None = None, ema: bool = True):
        from sefa_model.policy.artifact import Policy
        from sefa_model.policy.sampling import resolve_solver

        self.policy = Policy.load(path, device=device, ema=ema)  # "auto": sefa_model.distributed.resolve_device
        self.solver, self.steps = resolve_solver(self.policy.cfg, solver, steps)
        fps, _ = find_fps(self.policy)
        self.metadata = build_metadata(self.policy, "checkpoint", self.solver, self.steps, fps)
        self.device = str(self.policy.device)

    def __call__(self, obs: dict[str, np.ndarray], noise: np.ndarray, generator=None
                 ) -> tuple[np.ndarray, np.ndarray]:
        # `generator`: the diffusion sampler's later noises (a flow uses `noise` alone)
        out = self.policy.predict_action(obs, solver=self.solver, steps=self.steps,
                                         noise=torch.from_numpy(noise), generator=generator)
        return out.action.cpu().numpy(), out.action_pred.cpu().numpy()


def per_noise(obs: dict[str, np.ndarray], noise: np.ndarray) -> dict[str, np.ndarray]:
    """One observation (batch 1) repeated for each of N noises: an export's graph takes an
    observation per noise (a checkpoint's policy encodes the one observation once)."""
    n = noise.shape[0]
    return {k: np.repeat(v, n, axis=0) if v.shape[0] == 1 and n > 1 else v
            for k, v in obs.items()}


class TorchScriptBackend:
    """A traced module runs where it was traced: the CPU (tensors the trace made, such as the
    solver's time, carry the tracing device as a constant)."""

    name = "torchscript"

    def __init__(self, directory: Path, metadata: dict, *, device: str = "cpu"):
        if device not in ("cpu", "auto"):
            raise SefaInputError(f"a TorchScript export runs on the CPU it was traced on, not "
                                 f"'{device}'; serve the ONNX export or the checkpoint on a GPU",
                                 file=str(directory), key="--device")
        self.metadata = metadata
        self.device = torch.device("cpu")
        with warnings.catch_warnings():  # torch 2.13 marks TorchScript deprecated; it still loads
            warnings.simplefilter("ignore", DeprecationWarning)
            self.module = torch.jit.load(str(directory / metadata["file"]), map_location=self.device)
        self.keys = metadata["inputs"][:-1]

    @torch.inference_mode()
    def __call__(self, obs, noise, generator=None):  # an export's sampler draws nothing more
        obs = per_noise(obs, noise)
        action, chunk = self.module(*[torch.from_numpy(obs[k]) for k in self.keys],
                                    torch.from_numpy(noise))
        return action.numpy(), chunk.numpy()


class OnnxBackend:
    name = "onnx"

    def __init__(self, directory: Path, metadata: dict, *, device: str = "cpu"):
        try:
            import onnxruntime as ort
        except ImportError:
            raise SefaInputError("serving an ONNX export needs onnxruntime (pip install "
                                 "'sefa[deploy]')", file=str(directory)) from None

        self.metadata = metadata
        providers = ["CPUExecutionProvider"]
        gpu = "CUDAExecutionProvider" in ort.get_available_providers()
        if device == "auto":
            device = "cuda" if gpu else "cpu"
        if device.startswith("cuda"):
            if not gpu:
                raise SefaInputError("this onnxruntime has no CUDA provider (install "
                                     "onnxruntime-gpu, or serve with --device cpu)", key="--device")
            index = device.partition(":")[2] or "0"
            providers = [("CUDAExecutionProvider", {"device_id": int(index)}), *providers]
        self.device = device
        self.session = ort.InferenceSession(str(directory / metadata["file"]), providers=providers)
        self.names = list(zip(metadata["onnx_input_names"][:-1], metadata["inputs"][:-1]))

    def __call__(self, obs, noise, generator=None):  # an export's sampler draws nothing more
        obs = per_noise(obs, noise)
        feeds = {name: obs[key] for name, key in self.names}
        feeds["noise"] = noise
        action, chunk = self.session.run(["action", "action_pred"], feeds)
        return action, chunk


def load_backend(path: str | Path, *, device: str = "auto", solver: str | None = None,
                 steps: int | None = None, ema: bool = True):
    """An export directory (metadata.json beside the artifact) or a checkpoint / run dir.
    device "auto": a GPU when there is one and the backend can use it, else the CPU."""
    path = Path(path)
    if not (path / METADATA_FILE).exists():
        return CheckpointBackend(path, device=device, solver=solver, steps=steps, ema=ema)
    metadata = open_export(path)
    if not ema:
        raise SefaInputError("an export holds the weights it was exported with; --raw-weights "
                             "applies to checkpoints", file=str(path), key="--raw-weights")
    if solver is not None or steps is not None:
        raise SefaInputError(f"an export runs the setting it was exported with "
                             f"({metadata['solver']}-{metadata['steps']}); --solver and --steps "
                             f"apply to checkpoints", file=str(path))
    if not (path / str(metadata.get("file"))).is_file():
        raise SefaInputError(f"the export's file '{metadata.get('file')}' is missing", file=str(path))
    backends = {"onnx": OnnxBackend, "torchscript": TorchScriptBackend}
    if metadata["format"] not in backends:
        raise SefaInputError(f"unknown export format '{metadata['format']}'",
                             file=str(path / METADATA_FILE))
    backend = backends[metadata["format"]](path, metadata, device=device)
    probe(backend, path)
    return backend


def probe(backend, directory: Path) -> None:
    """The artifact run once on zeros of the shapes metadata.json names: it must take them and
    answer the shapes it names, else the metadata does not describe this artifact (edited, or
    beside another export's file) and every request would fail."""
    meta = backend.metadata
    obs = {k: np.zeros((1, *v["shape"]), v["dtype"]) for k, v in meta["obs"].items()}
    noise = np.zeros((1, *meta["noise"]["shape"]), np.float32)
    try:
        action, chunk = backend(obs, noise)
    except Exception as e:  # noqa: BLE001  onnxruntime's and TorchScript's errors have no common type
        raise SefaInputError(f"the exported {meta['file']} does not take the inputs metadata.json "
                             f"names ({type(e).__name__}: {' '.join(str(e).split())[:200]}): the "
                             "two are not from one export; export again",
                             file=str(directory / METADATA_FILE)) from None
    for name, got, want in (("action", action, meta["outputs"]["action"]["shape"]),
                            ("action_pred", chunk, meta["outputs"]["action_pred"]["shape"])):
        if tuple(np.shape(got)) != (1, *want):
            raise SefaInputError(f"the exported {meta['file']} answers {name} of shape "
                                 f"{tuple(np.shape(got))[1:]}, metadata.json says {tuple(want)}: "
                                 "the two are not from one export; export again",
                                 file=str(directory / METADATA_FILE))
