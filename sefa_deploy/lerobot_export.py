"""`sefa export POLICY --format lerobot --out DIR`: a folder LeRobot's own tools load as a policy
(`lerobot-eval --policy.path=DIR`, `lerobot-rollout`, the async policy server), with the
`lerobot_policy_sefa` plugin installed. The folder's layout is sefa_deploy/lerobot_format.py's.

    export_lerobot("distill", "deploy/lerobot")                        # names by default_name
    export_lerobot("distill", "out", names={"keypoint": "observation.environment_state"},
                   points={"keypoint": W})                               # W: (9, 8) corner weights

Written as LeRobot 0.6 writes a policy (config.json with its `type`, model.safetensors, the
pre- and postprocessor JSON), by this module and without LeRobot: sefa runs on Python 3.10+,
LeRobot 0.5+ on 3.12+. Whether LeRobot really loads it is the plugin's tests' job
(integrations/lerobot/tests, with the real lerobot-eval, rollout and policy server).

Before the folder is renamed into place it is loaded back (`ChunkModel`) and run on a real
window of the policy's store, in LeRobot's names (through the input map), and its chunk must be
finite and within the tolerance of `Policy.predict_action`'s for the same observation and noise,
as for the other formats (`check_artifact`). The folder appears only complete.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Mapping

import numpy as np
import torch

from sefa_data import atomic
from sefa_data.errors import NonFiniteError, SefaInputError
from sefa_deploy.export import ARTIFACT_TOLERANCE, example_inputs, real_window, relative_gap
from sefa_deploy.lerobot_format import (ACTION, CONFIG_FILE, FILES, FORMAT, POLICY_TYPE,
                                        POSTPROCESSOR_FILE, PREPROCESSOR_FILE, WEIGHTS_FILE,
                                        ChunkModel, InputMap, feature_shape, feature_type,
                                        input_map)
from sefa_deploy.metadata import find_fps, find_store
from sefa_model.policy.artifact import Policy
from sefa_model.policy.checkpoint import checkpoint_digest
from sefa_model.policy.execution import ExecutionSettings, resolve_execution
from sefa_model.policy.sampling import resolve_solver

DEVICE_STEP = {"registry_name": "device_processor", "config": {"device": "cpu", "float_dtype": None}}


def lerobot_config(policy: Policy, inputs: list[InputMap], solver: str, steps: int | None,
                   execution: ExecutionSettings, fps: float | None) -> dict:
    """config.json: LeRobot's fields, the executor's settings and the `sefa` section."""
    cfg = policy.cfg
    p, obs = cfg.policy, cfg.shape_meta.obs
    features = {m.feature: {"type": feature_type(m.feature), "shape": feature_shape(obs[m.key], m)}
                for m in inputs}
    from sefa_model.config import config_to_dict

    return {
        "type": POLICY_TYPE,
        "n_obs_steps": p.n_obs_steps,
        "input_features": features,
        "output_features": {ACTION: {"type": "ACTION", "shape": [cfg.shape_meta.action.shape[-1]]}},
        "device": None,  # LeRobot picks one (CUDA, MPS, the CPU); --policy.device sets it
        "horizon": p.horizon,
        "n_action_steps": p.n_action_steps,
        "solver": solver,
        "steps": steps,
        # sefa_model/policy/execution.py's settings, as given (unset ones resolved per run)
        "execution": execution.to_json(),
        "sefa": {
            "format": FORMAT,
            "sefa_version": _version(),
            "kind": policy.kind,
            "checkpoint": str(policy.path),
            "checkpoint_digest": checkpoint_digest(Path(policy.path)),
            "weights": policy.weights,
            "fps": fps,
            "action_key": cfg.shape_meta.action.key,
            "inputs": [m.to_json() for m in inputs],
            "normalizer": policy.normalizer.to_config(),
            "train_config": config_to_dict(cfg),
        },
    }


def processor_files() -> dict[str, dict]:
    """LeRobot's standard pre- and postprocessor (lerobot_format's docstring says why no
    normalizer steps): rename (LeRobot's --rename_map), batch, device."""
    return {
        PREPROCESSOR_FILE: {"name": "policy_preprocessor", "steps": [
            {"registry_name": "rename_observations_processor", "config": {"rename_map": {}}},
            {"registry_name": "to_batch_processor", "config": {}},
            DEVICE_STEP]},
        POSTPROCESSOR_FILE: {"name": "policy_postprocessor", "steps": [DEVICE_STEP]},
    }


def execution_settings(checkpoint, asked: ExecutionSettings | None, solver: str,
                       steps: int | None) -> tuple[ExecutionSettings, str]:
    """What config.json records: the settings asked for, else the execution chosen for this
    policy at this sampler setting (`sefa choose-execution`), else receding horizon; checked
    against the policy (ConfigError naming the option). bid is refused: it contrasts the policy
    with a second, weaker one, which a LeRobot folder does not carry."""
    settings, source, _ = resolve_execution(checkpoint, asked, solver, steps)
    if settings.mode == "bid":
        raise SefaInputError(f"{settings.label} ({source}) contrasts the policy with a weaker "
                             "one, which a LeRobot policy folder does not carry: export with "
                             "--execution receding, ensemble or coherent", key="--execution")
    recorded = asked if asked is not None else (settings if source == "chosen"
                                                else ExecutionSettings())
    return recorded, f"{settings.label} ({source})"


def lerobot_window(policy: Policy, inputs: list[InputMap], window: tuple
                   ) -> tuple[dict[str, torch.Tensor], dict[str, np.ndarray]]:
    """A store window (real_window's tensors) as LeRobot hands it over, and the store-named
    observation the policy then reads. A key reached through points gets the feature points
    that best give the window's (least squares), and the reference reads what they give, so
    the check compares one observation both ways."""
    frames = dict(zip(policy.cfg.shape_meta.obs, window))
    lerobot, store = {}, {}
    for m in inputs:
        spec = policy.cfg.shape_meta.obs[m.key]
        x = frames[m.key].numpy()
        if spec.type == "rgb":  # LeRobot: float CHW in [0, 1]
            lerobot[m.feature] = torch.from_numpy(np.moveaxis(x, -1, -3).astype(np.float32) / 255)
            store[m.key] = x
        elif m.points is not None:
            w = np.asarray(m.points)  # (K, S)
            kp = x.reshape(-1, *x.shape[-2:]).astype(np.float64)  # (N, K, 2)
            rhs = kp.transpose(1, 0, 2).reshape(len(w), -1)  # (K, N * 2)
            src = np.linalg.lstsq(w, rhs, rcond=None)[0]  # (S, N * 2)
            src = src.reshape(w.shape[1], -1, 2).transpose(1, 0, 2).astype(np.float32)
            lerobot[m.feature] = torch.from_numpy(src.reshape(*x.shape[:2], -1))
            store[m.key] = np.einsum("ks,nsd->nkd", w, src).reshape(x.shape).astype(np.float32)
        else:
            lerobot[m.feature] = torch.from_numpy(x.reshape(*x.shape[:2], -1).astype(np.float32))
            store[m.key] = x
    return lerobot, store


def check_folder(tmp: Path, policy: Policy, inputs: list[InputMap], window: tuple, where: str,
                 tolerance: float) -> float:
    """Load the written folder as the plugin does and compare its chunk with predict_action's."""
    config = json.loads((tmp / CONFIG_FILE).read_text())
    model = ChunkModel(config["sefa"], config["solver"], config["steps"]).load(tmp / WEIGHTS_FILE)
    lerobot, store = lerobot_window(policy, inputs, window)
    noise = window[-1]
    with torch.inference_mode():
        chunk = model(lerobot, noise).numpy()
    if not np.isfinite(chunk).all():
        raise NonFiniteError(f"the LeRobot export outputs NaN or Inf on {where}; nothing is "
                             "published", file=policy.path)
    want = policy.predict_action(store, solver=config["solver"], steps=config["steps"],
                                 noise=noise).action_pred.numpy()
    scale = policy.normalizer.params[policy.cfg.shape_meta.action.key].scale
    rel = relative_gap(chunk, want, scale)
    if not rel <= tolerance:
        raise SefaInputError(f"the LeRobot export differs from the checkpoint by "
                             f"{float(np.abs(chunk - want).max()):.3g} in action units, {rel:.3g} "
                             f"of the action's range (more than {tolerance:g}) on {where}; nothing "
                             "is published (an exporter problem: please report it)",
                             file=policy.path)
    return rel


def export_lerobot(checkpoint: str | Path, out: str | Path, *,
                   names: Mapping[str, str] | None = None,
                   points: Mapping[str, np.ndarray] | None = None,
                   solver: str | None = None, steps: int | None = None,
                   execution: ExecutionSettings | None = None, fps: float | None = None,
                   ema: bool = True, tolerance: float = ARTIFACT_TOLERANCE,
                   log=lambda _: None) -> dict:
    """Write the LeRobot policy folder `out`; returns its config.json. `names`: store key ->
    LeRobot name (the rest by lerobot_format.default_name); `points`: store key -> its affine
    weights from a feature's points (lerobot_format's docstring); `execution`: how LeRobot's
    select_action executes chunks (None: the execution chosen for the policy, else receding)."""
    out = Path(out)
    if out.exists() and not (out / CONFIG_FILE).exists():
        raise SefaInputError("exists and is not a policy folder; choose another --out", file=str(out))
    if not (isinstance(tolerance, (int, float)) and 0 < tolerance < 1):
        raise SefaInputError(f"{tolerance!r} is not a tolerance: a fraction of the action's "
                             "range, in (0, 1) (default 0.001)", key="--tolerance")
    policy = Policy.load(checkpoint, device="cpu", ema=ema)
    if policy.cfg.objective != "flow":
        raise SefaInputError(f"only flow policies are exported; this checkpoint is the "
                             f"{policy.cfg.objective} baseline", file=policy.path)
    if len(policy.cfg.shape_meta.action.shape) != 1:
        raise SefaInputError(f"LeRobot's action is one vector; this policy's is "
                             f"{policy.cfg.shape_meta.action.shape}", file=policy.path)
    solver, steps = resolve_solver(policy.cfg, solver, steps)
    inputs = input_map(policy.cfg, names, points)
    settings, executes = execution_settings(checkpoint, execution, solver, steps)
    store = find_store(policy)
    if fps is None:
        fps, _ = find_fps(policy)
    window = real_window(policy, store) if store is not None else example_inputs(policy, batch=1)
    where = f"a window of {store.path}" if store is not None else "random inputs (no store found)"
    config = lerobot_config(policy, inputs, solver, steps, settings, fps)
    tmp = atomic.tmp_name(out)
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    try:
        _write(tmp, policy, config)
        gap = check_folder(tmp, policy, inputs, window, where, tolerance)
        atomic.replace_dir(tmp, out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    for m in inputs:
        log(f"LeRobot's {m.feature} {config['input_features'][m.feature]['shape']} -> {m.key}"
            + (" (through its points)" if m.points is not None else ""))
    log(f"select_action executes {executes}")
    log(f"checked the folder on {where}: finite actions, within {gap:.2g} of the action's range "
        f"of the checkpoint's (tolerance {tolerance:g})")
    log(f"wrote {out} ({', '.join(FILES)}): lerobot-eval --policy.path={out} with the "
        "lerobot_policy_sefa plugin installed")
    return config


def _write(tmp: Path, policy: Policy, config: dict) -> None:
    from safetensors.torch import save_file

    model = ChunkModel(config["sefa"], config["solver"], config["steps"])
    model.model.load_state_dict(policy.model.state_dict())
    model.set_normalizer(policy.normalizer)
    save_file(model.state_tensors(), str(tmp / WEIGHTS_FILE),
              metadata={"format": "pt"})
    (tmp / CONFIG_FILE).write_text(json.dumps(config, indent=2, allow_nan=False))
    for name, value in processor_files().items():
        (tmp / name).write_text(json.dumps(value, indent=2))


def _version() -> str | None:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("sefa")
    except PackageNotFoundError:
        return None
