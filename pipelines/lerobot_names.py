"""Which LeRobot observation feeds which of a policy's keys when it is exported for LeRobot
(`sefa export --format lerobot`): `--key-map NAME=KEY` pairs first, then LeRobot's usual names
(sefa_deploy.lerobot_format.default_name), and for a policy of Diffusion Policy's Push-T store
the map from gym-pusht's keypoints to the store's.

Push-T: the store's `keypoint` is 9 points fixed in the block (sefa_sim.pusht.LOCAL_KEYPOINTS),
while gym-pusht, and so LeRobot's `--env.type=pusht --env.obs_type=environment_state_agent_pos`,
observes the T's 8 corners as `observation.environment_state` (16 values). Both are the same
rigid body placed by one pose, so the 9 points are fixed affine combinations of the 8 corners
(sefa_sim.pusht.affine_weights): the export carries that (9, 8) matrix and the policy applies it,
giving what `sefa eval --env pusht` feeds the policy (to float32 rounding). `state` (agent x, y,
block pose) is read through `dims` [0, 2] by these policies: LeRobot's `observation.state` is the
agent's position, exactly that slice. This lives here, not in sefa_deploy, because the geometry
is the simulator's (sefa_sim), which sefa_deploy does not import.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Mapping

import numpy as np

from sefa_data.errors import SefaInputError
from sefa_deploy.lerobot_format import ENV_STATE

PUSHT_KEYPOINT = "keypoint"


def store_names(key_map: Mapping[str, str] | None) -> dict[str, str]:
    """`--key-map NAME=KEY` (LeRobot's NAME feeds the policy's KEY, as for `sefa serve` and
    `sefa eval`) -> {KEY: NAME}; a key named twice is one line."""
    out: dict[str, str] = {}
    for name, key in (key_map or {}).items():
        if not key:
            raise SefaInputError(f"'{name}=': an export maps every LeRobot name to a policy key",
                                 key="--key-map")
        if key in out:
            raise SefaInputError(f"'{key}' is named twice ({out[key]}, {name})", key="--key-map")
        out[key] = name
    return out


def pusht_points(obs: Mapping, names: Mapping[str, str]) -> dict[str, np.ndarray]:
    """The Push-T corner map when the policy reads the store's 9 keypoints and they come from
    LeRobot's environment state; else nothing."""
    from sefa_sim.pusht import GYM_PUSHT_CORNERS, LOCAL_KEYPOINTS, affine_weights

    spec = obs.get(PUSHT_KEYPOINT)
    if spec is None or list(spec.frame_shape or []) != list(LOCAL_KEYPOINTS.shape):
        return {}
    if names.get(PUSHT_KEYPOINT, ENV_STATE) != ENV_STATE:
        return {}
    return {PUSHT_KEYPOINT: affine_weights(GYM_PUSHT_CORNERS, LOCAL_KEYPOINTS)}


def lerobot_execution(mode: str | None, replan_every: int | None = None,
                      samples: int | None = None, decay: float | None = None,
                      ensemble_k: float | None = None):
    """`sefa export --format lerobot`'s --execution options as ExecutionSettings (None: none
    given); bid refused (options.export_execution)."""
    from sefa_pipelines.options import export_execution

    return export_execution(mode, replan_every, samples, decay, ensemble_k,
                            "a LeRobot policy folder")


def export_for_lerobot(checkpoint: Path, out: Path, *, key_map: Mapping[str, str] | None,
                       log: Callable[[str], None] = lambda _: None, **options) -> dict:
    """`sefa export --format lerobot`: the names and the Push-T map, then the export."""
    from sefa_deploy.lerobot_export import export_lerobot
    from sefa_model.config import saved_train_config
    from sefa_model.policy.checkpoint import open_policy

    names = store_names(key_map)
    _, meta, _ = open_policy(checkpoint, options.get("ema", True))
    cfg = saved_train_config(meta["train_config"], source=str(checkpoint))
    points = pusht_points(cfg.shape_meta.obs, names)
    if points:
        log("Push-T: the store's 9 keypoints from gym-pusht's 8 T corners "
            "(observation.environment_state), as sefa eval --env pusht computes them")
    return export_lerobot(checkpoint, out, names=names, points=points, log=log, **options)
