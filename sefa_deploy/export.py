"""A trained flow policy as one self-contained file: ONNX or TorchScript (`sefa export`).

    export_policy("distill", "deploy/", fmt="onnx")            # a one-step policy
    export_policy("train", "deploy/", fmt="torchscript", solver="euler", steps=4)

The artifact maps the raw observation and a noise tensor to the action chunk in robot units,
with everything `Policy.predict_action` does inside it:

    inputs   one tensor per observation key, (B, To, *frame_shape) as the store holds the frames
             (low-dim: float32 in the store's units; images: uint8 HWC), then `noise`
             (B, horizon, Da) float32, standard normal. Each is named by its store key as it
             is (`observation.state`; ONNX names may hold '.' and '/', and onnxruntime feeds
             them by name), in the order of `shape_meta.obs` in the checkpoint's config.json
             (`shape_meta.obs_keys` when the training named them, else the store's keys by
             name), then `noise`: metadata.json's `inputs`, the positional order TorchScript
             takes
    inside   low-dim `dims` slice + normalization, images to CHW in [0, 1], the observation
             encoder, the fixed-step solver unrolled (Euler-N: N velocity evaluations; a
             one-step policy: one), unnormalization of the chunk
    outputs  `action` (B, n_action_steps, Da): the steps to execute now; `action_pred`
             (B, horizon, Da): the whole chunk

Beside it, `metadata.json` (see `sefa_deploy.metadata.build_metadata`) names the inputs in
order with their shapes and dtypes, n_obs_steps, n_action_steps, fps, which steps of the chunk
`action` is, and the checkpoint it came from (`checkpoint`, `checkpoint_resolved`: the run
folder behind a workspace's pointer, `checkpoint_digest`:
`sefa_model.policy.checkpoint.checkpoint_digest`), from which `sefa status` tells an export made before
a retraining. The noise is
an input, not drawn inside, so that a caller controls reproducibility (and parity with
`predict_action` can be checked exactly); `sefa serve` draws it. `checksums.json` records the size
and SHA-256 of both files, so that an export is served only as it was written
(`sefa_deploy.metadata.open_export`).

Nothing non-finite is published: `Policy.load` refuses damaged or non-finite weights, and before
the directory is renamed into place the artifact itself (loaded with onnxruntime or torch.jit, as
a robot would) runs on a real observation window from the policy's store (random inputs of the
right shapes when the store is not found) and must return finite actions equal to
`predict_action`'s for the same noise (`check_artifact`).

Only fixed-step flows can be unrolled: an adaptive solver (rk45) chooses its steps from the data
at run time, and the diffusion baseline is not exported. The EMA weights are exported, as
`Policy.load` uses them.

Which exporter: ONNX goes through `torch.onnx.export(dynamo=True)` (torch.export + onnxscript,
the exporter PyTorch maintains; the TorchScript-based one is deprecated), with the batch axis
dynamic. Which runtime can load it: `opset` (OPSETS, default DEFAULT_OPSET) is the exporter's
`opset_version`; the file is then stamped with the lowest IR version that opset belongs to (the
exporter stamps the IR of the onnx library it runs with, IR 10 with onnx >= 1.16, which
onnxruntime 1.17 and older refuse: "Unsupported model IR version: 10"), checked with
onnx.checker, and metadata.json records `onnx_opset`, `onnx_ir_version` and
`min_onnxruntime`, the first onnxruntime release that implements both (its compatibility
table, ORT_RELEASES). Below opset 18 the exporter cannot go: torch falls back to 18 when the
onnx version converter cannot lower an op, and Mish, in every sefa head, has no version before
18. TorchScript goes through `torch.jit.trace`: the network has no data-dependent control
flow, and a traced module loads with `torch.jit.load` from torch alone, without sefa.
"""

from __future__ import annotations

import json
import logging
import shutil
import warnings
from pathlib import Path

import numpy as np
import torch
from torch import nn

from sefa_data import atomic
from sefa_data.errors import NonFiniteError, SefaInputError
from sefa_deploy.backends import OnnxBackend, TorchScriptBackend
from sefa_deploy.metadata import (FORMATS, METADATA_FILE, NFE_PER_STEP, build_metadata, find_fps,
                                  find_store)
from sefa_model.policy.artifact import Policy
from sefa_model.policy.checkpoint import write_checksums
from sefa_model.policy.sampling import resolve_solver

OPSETS = range(18, 22)  # `sefa export --opset`: 18 .. 21
DEFAULT_OPSET = 20  # torch 2.13's own default: IR 9, onnxruntime >= 1.17
# onnxruntime's compatibility table (onnxruntime.ai/docs/reference/compatibility.html):
# (release, the newest ai.onnx opset it implements, the newest IR version it loads)
ORT_RELEASES = [("1.14", 18, 8), ("1.15", 19, 8), ("1.16", 19, 9), ("1.17", 20, 9),
                ("1.18", 21, 10)]


def ir_version_of(opset: int) -> int:
    """The IR version of the onnx release that introduced ai.onnx `opset`: the lowest a model
    of that opset may be stamped with."""
    from onnx import helper

    return min(ir for _, ir, ai_onnx, *_ in helper.VERSION_TABLE if ai_onnx >= opset)


def min_onnxruntime(opset: int, ir_version: int) -> str:
    for release, max_opset, max_ir in ORT_RELEASES:
        if max_opset >= opset and max_ir >= ir_version:
            return release
    raise ValueError(f"no known onnxruntime release loads opset {opset}, IR {ir_version}")


class ExportedPolicy(nn.Module):
    """`Policy.predict_action` as one traceable module: forward(*obs_in_key_order, noise)
    -> (action, action_pred), both in action units. The policy's own processor and sampler are
    wrapped, not copied: their buffers (the normalizer) travel inside the artifact."""

    def __init__(self, policy: Policy, solver: str, steps: int):
        super().__init__()
        cfg = policy.cfg
        self.model = policy.model.eval().requires_grad_(False)  # outputs need no autograd graph
        self.processor = policy.processor
        self.keys = list(cfg.shape_meta.obs)
        self.solver, self.steps = solver, steps
        self.start = cfg.policy.n_obs_steps - 1  # DP: act from the current (last observed) frame on
        self.n_action_steps = cfg.policy.n_action_steps

    def forward(self, *inputs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        *frames, noise = inputs
        cond = self.model.encode(self.processor.obs(dict(zip(self.keys, frames))))
        # the same sampler as predict_action; its Python loop unrolls into the graph
        x = self.model.sample(cond, noise, solver=self.solver, steps=self.steps).x
        chunk = self.processor.action.unnormalize(x)
        return chunk[:, self.start:self.start + self.n_action_steps], chunk


def export_solver(policy: Policy, solver: str | None, steps: int | None) -> tuple[str, int]:
    """The fixed-step setting to unroll: the checkpoint's own, or the one asked for."""
    cfg = policy.cfg
    if not policy.model.method.solves_ode:
        raise SefaInputError(f"only flow policies are exported; this checkpoint is the "
                             f"{policy.model.method.name} baseline", file=policy.path)
    solver, steps = resolve_solver(cfg, solver, steps)
    if solver not in NFE_PER_STEP or steps is None:
        raise SefaInputError(f"the solver '{solver}' is adaptive and cannot be unrolled into a "
                             f"fixed graph; export a fixed-step setting, e.g. --solver euler "
                             f"--steps 4", file=policy.path, key="--solver")
    return solver, steps


def example_inputs(policy: Policy, batch: int = 2) -> tuple[torch.Tensor, ...]:
    """Inputs of the right shapes and dtypes, for tracing."""
    cfg = policy.cfg
    gen = torch.Generator().manual_seed(0)
    out = []
    for spec in cfg.shape_meta.obs.values():
        shape = (batch, cfg.policy.n_obs_steps, *spec.frame_shape)
        out.append(torch.randint(0, 256, shape, generator=gen, dtype=torch.uint8) if spec.type == "rgb"
                   else torch.randn(shape, generator=gen))
    out.append(torch.randn(batch, cfg.policy.horizon, cfg.shape_meta.action.shape[-1], generator=gen))
    return tuple(out)


def real_window(policy: Policy, store) -> tuple[torch.Tensor, ...]:
    """The first n_obs_steps frames of the store's first episode, as the artifact's inputs
    (batch 1), then a fixed noise."""
    cfg = policy.cfg
    to = cfg.policy.n_obs_steps
    episode = store.get_episode(0, keys=list(cfg.shape_meta.obs))
    frames = []
    for key in cfg.shape_meta.obs:
        x = np.asarray(episode[key][:to])
        x = np.concatenate([x, np.repeat(x[-1:], to - len(x), axis=0)]) if len(x) < to else x
        frames.append(torch.from_numpy(np.ascontiguousarray(x[None])))
    gen = torch.Generator().manual_seed(0)
    noise = torch.randn(1, cfg.policy.horizon, cfg.shape_meta.action.shape[-1], generator=gen)
    return (*[f if f.dtype == torch.uint8 else f.float() for f in frames], noise)


# the artifact against predict_action, as a fraction of the action's range (the normalizer's:
# [min, max] for limits, 2 std for gaussian), never in robot units: float32 graphs differ by
# reassociation (ONNX's optimizer fuses ops), and in units such as Push-T's pixels (up to 511)
# that is above any absolute bound while far below what a robot notices; an exporter fault (a
# wrong op, a lost input) moves actions by a sizeable part of their range
ARTIFACT_TOLERANCE = 1e-3
# the absolute bound the tests compare a normalized gap of the shipped examples with
ARTIFACT_ATOL = 1e-3


def relative_gap(chunk: np.ndarray, want: np.ndarray, scale: np.ndarray) -> float:
    """The largest difference of two action chunks as a fraction of the action's range: the
    normalized difference (x * scale) over the normalized range's width, 2."""
    return float((np.abs(chunk - want) * np.abs(np.asarray(scale))).max() / 2.0)


def check_artifact(directory: Path, metadata: dict, policy: Policy, inputs: tuple,
                   where: str, tolerance: float = ARTIFACT_TOLERANCE) -> float:
    """Run the written artifact as a robot would and refuse to publish it when its actions are
    not finite or differ from predict_action's for the same observation and noise."""
    backend = (OnnxBackend if metadata["format"] == "onnx" else TorchScriptBackend)(
        directory, metadata, device="cpu")
    *frames, noise = inputs
    obs = {k: f.numpy() for k, f in zip(policy.cfg.shape_meta.obs, frames)}
    action, chunk = backend(obs, noise.numpy())
    if not (np.isfinite(action).all() and np.isfinite(chunk).all()):
        raise NonFiniteError(f"the exported policy outputs NaN or Inf on {where}; nothing is "
                             "published", file=policy.path)
    want = policy.predict_action(obs, solver=metadata["solver"], steps=metadata["steps"],
                                 noise=noise).action_pred.numpy()
    gap = float(np.abs(chunk - want).max())
    rel = relative_gap(chunk, want, metadata["action_normalizer"]["scale"])
    if not rel <= tolerance:
        raise SefaInputError(f"the exported policy differs from the checkpoint by {gap:.3g} in "
                             f"action units, {rel:.3g} of the action's range (more than the "
                             f"tolerance {tolerance:g}, --tolerance) on {where}; nothing is "
                             "published (an exporter problem: please report it)", file=policy.path)
    return rel


def export_policy(checkpoint: str | Path, out: str | Path, *, fmt: str = "onnx",
                  solver: str | None = None, steps: int | None = None, fps: float | None = None,
                  ema: bool = True, opset: int = DEFAULT_OPSET,
                  tolerance: float = ARTIFACT_TOLERANCE, execution=None,
                  log=lambda _: None) -> dict:
    """Write `out/policy.onnx` or `out/policy.pt` and `out/metadata.json`; returns the metadata.
    The directory is built under a temporary name and renamed into place. `execution`
    (ExecutionSettings): what `sefa serve` runs for it (None: the one chosen for the policy)."""
    if fmt not in FORMATS:
        raise SefaInputError(f"unknown export format '{fmt}' (use one of {', '.join(FORMATS)})",
                             key="--format")
    if opset not in OPSETS or isinstance(opset, bool):
        raise SefaInputError(f"{opset!r} is not supported (valid: {OPSETS.start} to "
                             f"{OPSETS.stop - 1}; 18 loads in onnxruntime >= 1.14)", key="--opset")
    if not (isinstance(tolerance, (int, float)) and 0 < tolerance < 1):
        raise SefaInputError(f"{tolerance!r} is not a tolerance: a fraction of the action's "
                             "range, in (0, 1) (default 0.001)", key="--tolerance")
    if fmt != "onnx" and opset != DEFAULT_OPSET:
        raise SefaInputError("an opset is an ONNX setting; a TorchScript export has none",
                             key="--opset")
    out = Path(out)
    if out.exists() and not (out / METADATA_FILE).exists():
        raise SefaInputError("exists and is not a sefa export; choose another --out", file=str(out))
    policy = Policy.load(checkpoint, device="cpu", ema=ema)
    solver, steps = export_solver(policy, solver, steps)
    if execution is not None:  # checked against the policy before anything is written
        execution = execution.resolved(policy.cfg.policy.n_action_steps)
    names = list(policy.cfg.shape_meta.obs)  # the inputs are named by the store's keys
    if "noise" in names:
        raise SefaInputError("an observation key named 'noise' would collide with the noise "
                             "input; rename it at ingest (--rename noise=...)", file=policy.path)
    store = find_store(policy)
    if fps is None:
        fps, source = find_fps(policy)
        log(f"fps: {fps:g} (from {source})" if fps is not None else f"fps: unknown ({source})")
    module = ExportedPolicy(policy, solver, steps).eval()
    inputs = example_inputs(policy)
    check = ((real_window(policy, store), f"a window of {store.path}") if store is not None
             else (example_inputs(policy, batch=1), "random inputs (the store was not found)"))
    tmp = atomic.tmp_name(out)
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    try:
        path = tmp / FORMATS[fmt]
        if fmt == "onnx":
            versions = write_onnx(module, inputs, path, names=names, opset=opset)
        else:
            write_torchscript(module, inputs, path)
        metadata = build_metadata(policy, fmt, solver, steps, fps, execution)
        if fmt == "onnx":  # the store's keys; kept for readers of exports before issue 25,
            metadata["onnx_input_names"] = [*names, "noise"]  # whose names were identifiers
            metadata.update(versions)
        (tmp / METADATA_FILE).write_text(json.dumps(metadata, indent=2, allow_nan=False))
        write_checksums(tmp)  # served only as written (sefa_deploy/metadata.py:open_export)
        gap = check_artifact(tmp, metadata, policy, *check, tolerance=tolerance)
        atomic.replace_dir(tmp, out)  # an earlier export (checked above) is kept until the swap
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    log(f"checked the artifact on {check[1]}: finite actions, within {gap:.2g} of the action's "
        f"range of the checkpoint's (tolerance {tolerance:g})")
    log(f"wrote {out / FORMATS[fmt]} ({solver}-{steps}, {metadata['nfe']} network evaluation(s)) "
        f"and {out / METADATA_FILE}")
    if fmt == "onnx":
        log(f"ONNX opset {metadata['onnx_opset']}, IR {metadata['onnx_ir_version']}: loads in "
            f"onnxruntime >= {metadata['min_onnxruntime']}")
    return metadata


def write_torchscript(module: nn.Module, inputs: tuple, path: Path) -> None:
    with torch.inference_mode(False), torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the tracer's notes on Python floats made constants
        traced = torch.jit.trace(module, inputs, check_trace=False)
    torch.jit.save(traced, str(path))


def write_onnx(module: nn.Module, inputs: tuple, path: Path, names: list[str],
               opset: int = DEFAULT_OPSET) -> dict:
    """-> the versions metadata.json records (the module docstring says why these)."""
    from torch.export import Dim

    batch = Dim("batch")
    dynamic = tuple({0: batch} for _ in inputs)
    quiet = logging.getLogger("torch.onnx")  # "torchvision is not installed" and the like
    level = quiet.level
    quiet.setLevel(logging.ERROR)
    try:
        with torch.no_grad(), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            program = torch.onnx.export(module, inputs, dynamo=True, dynamic_shapes=(dynamic,),
                                        input_names=[*names, "noise"],
                                        output_names=["action", "action_pred"],
                                        optimize=True, verbose=False, opset_version=opset)
    except ImportError as e:
        raise SefaInputError(f"ONNX export needs the deploy extra (pip install 'sefa[deploy]'): "
                             f"{e}", key="--format") from None
    finally:
        quiet.setLevel(level)
    import onnx

    model = program.model_proto
    opsets = {o.domain or "ai.onnx": o.version for o in model.opset_import}
    if opsets != {"ai.onnx": opset}:
        raise SefaInputError(f"the exporter wrote opsets {opsets}, not ai.onnx {opset} alone; "
                             "nothing is published (please report it)", key="--opset")
    model.ir_version = ir_version_of(opset)
    onnx.checker.check_model(model, full_check=True)
    onnx.save(model, str(path))
    return {"onnx_opset": opset, "onnx_ir_version": model.ir_version,
            "min_onnxruntime": min_onnxruntime(opset, model.ir_version)}
