"""Collect scripted Lift demonstrations into a robomimic-layout HDF5 file (the layout, and how a
file already there is treated: sefa_sim/demo_file.py).

Only successful episodes are kept; they are numbered demo_0.. in order with no gaps (after the
file's own with `append`); the seeds of the others are in the summary `collect_lift` returns (and
`sefa collect` prints).

Seeding: robosuite 1.5.1's Lift takes no `seed` argument and samples the cube pose and the
robot's initial joint noise from NumPy's global RNG, so episode i seeds `np.random.seed(seed+i)`
right before `env.reset()`. The expert's optional action noise has its own generator, seeded
with the same value, so an episode is reproducible on its own, whatever ran before it.

Run: python -m sefa_sim.collect OUT.hdf5 --episodes 50 --seed 0
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np


# importing anything from sefa_sim runs its __init__, which sets MUJOCO_GL; robosuite itself is
# imported only inside functions, after that
from sefa_sim.demo_file import Episode, plan_target, record, write_demos  # noqa: F401 (re-exported)
from sefa_sim.lift_expert import LiftExpert, LiftExpertConfig

ENV_NAME = "Lift"
LOW_DIM_KEYS = ("robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos",
                "robot0_joint_pos", "cube_pos", "cube_quat")
# robosuite calls the object vector "object-state"; robomimic datasets store it as "object"
OBJECT_KEY = ("object-state", "object")
DEFAULT_CAMERAS = ("agentview", "robot0_eye_in_hand")


def env_kwargs(cameras: bool = False, control_freq: int = 20, horizon: int = 500,
               camera_size: int = 84) -> dict[str, Any]:
    """suite.make keyword arguments, stored verbatim in env_args so robomimic can rebuild it."""
    import robosuite as suite

    controller = suite.load_composite_controller_config(controller="BASIC", robot="Panda")
    return {
        "robots": ["Panda"],
        # BASIC for a Panda is OSC_POSE on the arm with delta input, plus the GRIP gripper
        "controller_configs": controller,
        "has_renderer": False,
        "has_offscreen_renderer": cameras,
        "use_camera_obs": cameras,
        "use_object_obs": True,
        "ignore_done": True,  # the collector decides when an episode ends
        "reward_shaping": False,
        "control_freq": control_freq,
        "horizon": horizon,
        "camera_names": list(DEFAULT_CAMERAS),
        "camera_heights": camera_size,
        "camera_widths": camera_size,
        "camera_depths": False,
        # a hard reset rebuilds the model on every reset. Needed for seeding: Lift draws the cube's
        # size from the global RNG when it builds the model, so without it the size is fixed,
        # unseeded, at construction and episodes depend on what ran before them.
        "hard_reset": True,
    }


def make_env(kwargs: dict[str, Any]) -> Any:
    # robosuite's notes (the controller file at every reset, which rebuilds the model) are
    # filtered since sefa_sim was imported (sefa_sim/__init__.py: quiet_robosuite)
    import robosuite as suite

    return suite.make(ENV_NAME, **kwargs)


def run_episode(env: Any, expert: LiftExpert, seed: int, max_steps: int,
                cameras: bool = False) -> Episode:
    """One seeded episode; it ends at the first step where the cube is lifted, or max_steps."""
    np.random.seed(seed)
    obs = env.reset()
    expert.reset(obs, seed=seed)
    episode = Episode(seed=seed, success=False, model_file=env.sim.model.get_xml())
    keys = _obs_keys(obs, cameras)
    for _ in range(max_steps):
        for key, name in keys.items():
            episode.obs.setdefault(name, []).append(_frame(obs[key], name))
        episode.states.append(np.asarray(env.sim.get_state().flatten()))
        action = expert.act(obs)
        obs, reward, _, _ = env.step(action)
        episode.actions.append(action)
        episode.rewards.append(float(reward))
        if env._check_success():
            episode.success = True
            break
    episode.final_obs = {name: _frame(obs[key], name) for key, name in keys.items()}
    return episode


def _frame(value: np.ndarray, name: str) -> np.ndarray:
    """A copy of one observation; images turned upright.

    robosuite renders with the OpenGL convention (row 0 at the bottom); robomimic's robosuite
    wrapper flips images before storing them, and so do we, to match its datasets.
    """
    value = np.asarray(value)
    if name.endswith("_image") and _images_bottom_up():
        return value[::-1].copy()
    return value.copy()


def _images_bottom_up() -> bool:
    # a user's private robosuite macros may already switch to the opencv (top-down) convention
    from robosuite import macros

    return macros.IMAGE_CONVENTION == "opengl"


def _obs_keys(obs: dict[str, np.ndarray], cameras: bool) -> dict[str, str]:
    """robosuite observation key -> name stored under obs/."""
    keys = {k: k for k in LOW_DIM_KEYS if k in obs}
    if OBJECT_KEY[0] in obs:
        keys[OBJECT_KEY[0]] = OBJECT_KEY[1]
    if cameras:
        keys.update({f"{c}_image": f"{c}_image" for c in DEFAULT_CAMERAS if f"{c}_image" in obs})
    return keys


def collect_lift(out_path: str | Path, episodes: int, seed: int = 0, cameras: bool = False,
                 max_steps: int = 200, control_freq: int = 20,
                 expert_config: LiftExpertConfig | None = None, *, append: bool = False,
                 force: bool = False) -> dict[str, Any]:
    """Run `episodes` seeded episodes (seed, seed+1, ...), write the successful ones (`append`,
    `force`: what to do with a file already there; sefa_sim/demo_file.py).

    Returns demo_file.record's summary; `steps` counts the samples written.
    """
    target = plan_target(out_path, episodes, seed, append=append, force=force)
    kwargs = env_kwargs(cameras=cameras, control_freq=control_freq, horizon=max_steps + 1)
    env = make_env(kwargs)
    expert = LiftExpert(expert_config)
    try:
        return record(target, range(seed, seed + episodes),
                      lambda s: run_episode(env, expert, s, max_steps, cameras),
                      lift_env_args(kwargs))
    finally:
        env.close()


# ----------------------------------------------------------------------------- the file's env_args

def _robosuite_version() -> str:
    import robosuite

    return robosuite.__version__


def lift_env_args(kwargs: dict[str, Any]) -> dict[str, Any]:
    # type 1 is robomimic's EnvType.ROBOSUITE_TYPE; env_version is what robomimic compares with
    # the installed robosuite when it rebuilds the env
    return {"env_name": ENV_NAME, "env_version": _robosuite_version(), "type": 1,
            "env_kwargs": kwargs}


# ----------------------------------------------------------------------------- command line

def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Scripted robosuite Lift demos -> robomimic HDF5")
    parser.add_argument("out", type=Path)
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--max-steps", type=int, default=200)
    parser.add_argument("--noise", type=float, default=0.0, help="action noise std (pos/rot)")
    parser.add_argument("--cameras", action="store_true", help="also record camera images")
    args = parser.parse_args(argv)
    result = collect_lift(args.out, args.episodes, args.seed, cameras=args.cameras,
                          max_steps=args.max_steps,
                          expert_config=LiftExpertConfig(noise_std=args.noise))
    per_episode = result["seconds"] / max(args.episodes, 1)
    print(json.dumps({**result, "seconds_per_episode": round(per_episode, 3)}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
