"""Collect scripted Lift demonstrations into a robomimic-layout HDF5 file.

Layout written (what robomimic's SequenceDataset, with its default settings, and
`sefa_data.readers.hdf5` read):

    data.attrs: env_args (JSON: env_name, env_version, type=1, env_kwargs), total (samples)
    data/demo_{i}/obs/<key>   (T, ...) observation before action t
    data/demo_{i}/next_obs/<key> (T, ...) observation after action t (obs shifted by one, then
                                       the observation the last action led to)
    data/demo_{i}/actions     (T, 7)   float64 in [-1, 1]
    data/demo_{i}/rewards     (T,)     env reward after action t
    data/demo_{i}/dones       (T,)     1 on the last step
    data/demo_{i}/states      (T, S)   flattened MuJoCo state before action t
    data/demo_{i}.attrs: num_samples, model_file (MJCF, what robomimic uses to replay states),
                         seed (the reset seed that produced it)

    mask/train, mask/valid    demo names (bytes): a seeded 90/10 split, at least one demo in
                              each when there are two or more (robomimic's filter keys)

Only successful episodes are kept; they are numbered demo_0.. in order with no gaps; the seeds
of the others are in the summary `collect_lift` returns (and `sefa collect` prints).

Seeding: robosuite 1.5.1's Lift takes no `seed` argument and samples the cube pose and the
robot's initial joint noise from NumPy's global RNG, so episode i seeds `np.random.seed(seed+i)`
right before `env.reset()`. The expert's optional action noise has its own generator, seeded
with the same value, so an episode is reproducible on its own, whatever ran before it.

Run: python -m sefa_sim.collect OUT.hdf5 --episodes 50 --seed 0
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from sefa_data import atomic

# importing anything from sefa_sim runs its __init__, which sets MUJOCO_GL; robosuite itself is
# imported only inside functions, after that
from sefa_sim.lift_expert import LiftExpert, LiftExpertConfig

ENV_NAME = "Lift"
LOW_DIM_KEYS = ("robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos",
                "robot0_joint_pos", "cube_pos", "cube_quat")
# robosuite calls the object vector "object-state"; robomimic datasets store it as "object"
OBJECT_KEY = ("object-state", "object")
DEFAULT_CAMERAS = ("agentview", "robot0_eye_in_hand")


@dataclass
class Episode:
    seed: int
    success: bool
    obs: dict[str, list[np.ndarray]] = field(default_factory=dict)
    actions: list[np.ndarray] = field(default_factory=list)
    rewards: list[float] = field(default_factory=list)
    states: list[np.ndarray] = field(default_factory=list)
    final_obs: dict[str, np.ndarray] = field(default_factory=dict)  # after the last action
    model_file: str = ""

    def __len__(self) -> int:
        return len(self.actions)


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
    import logging

    import robosuite as suite
    from robosuite.utils.log_utils import ROBOSUITE_DEFAULT_LOGGER

    # every reset rebuilds the model and robosuite logs the same controller notes each time
    ROBOSUITE_DEFAULT_LOGGER.setLevel(logging.ERROR)
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
                 expert_config: LiftExpertConfig | None = None) -> dict[str, Any]:
    """Run `episodes` seeded episodes (seed, seed+1, ...), write the successful ones.

    Returns {attempted, successful, success_rate, steps, failed_seeds, seconds}; `steps` counts
    the samples written.
    """
    kwargs = env_kwargs(cameras=cameras, control_freq=control_freq, horizon=max_steps + 1)
    env = make_env(kwargs)
    expert = LiftExpert(expert_config)
    kept: list[Episode] = []
    failed: list[int] = []
    start = time.perf_counter()
    try:
        for i in range(episodes):
            episode = run_episode(env, expert, seed + i, max_steps, cameras)
            if episode.success:
                kept.append(episode)
            else:
                failed.append(episode.seed)
    finally:
        env.close()
    seconds = time.perf_counter() - start
    write_demos(Path(out_path), kept, lift_env_args(kwargs))
    return {
        "attempted": episodes,
        "successful": len(kept),
        "success_rate": len(kept) / episodes if episodes else 0.0,
        "steps": sum(len(e) for e in kept),
        "failed_seeds": failed,
        "seconds": seconds,
    }


# ----------------------------------------------------------------------------- writing

def _robosuite_version() -> str:
    import robosuite

    return robosuite.__version__


def lift_env_args(kwargs: dict[str, Any]) -> dict[str, Any]:
    # type 1 is robomimic's EnvType.ROBOSUITE_TYPE; env_version is what robomimic compares with
    # the installed robosuite when it rebuilds the env
    return {"env_name": ENV_NAME, "env_version": _robosuite_version(), "type": 1,
            "env_kwargs": kwargs}


def write_demos(path: Path, episodes: list[Episode], env_args: dict[str, Any],
                env_info: dict[str, Any] | None = None, val_ratio: float = 0.1,
                split_seed: int = 0) -> None:
    """Write next to the target and rename, so a reader never sees a half-written file.
    The writer of every simulator's demonstrations (Lift's and Meta-World's). `env_info`
    (data.attrs, JSON) carries what env_args cannot, such as a control_freq that is not an
    argument of the env."""
    with atomic.writing(path) as tmp, h5py.File(tmp, "w") as f:
        _write_file(f, episodes, env_args, val_ratio, split_seed)
        if env_info is not None:
            f["data"].attrs["env_info"] = json.dumps(env_info)


def _write_file(f: h5py.File, episodes: list[Episode], env_args: dict[str, Any],
                val_ratio: float = 0.1, split_seed: int = 0) -> None:
    from sefa_data.store.zarr_store import split_masks

    data = f.create_group("data")
    names = [f"demo_{i}" for i in range(len(episodes))]
    for name, episode in zip(names, episodes):
        _write_demo(data.create_group(name), episode)
    data.attrs["total"] = sum(len(e) for e in episodes)
    data.attrs["env_args"] = json.dumps(env_args)
    train, valid = split_masks(len(names), val_ratio, split_seed)
    for mask_name, chosen in (("train", train), ("valid", valid)):
        f.create_dataset(f"mask/{mask_name}", data=np.array(
            [n.encode() for n, keep in zip(names, chosen) if keep], dtype="S"))


def _write_demo(group: h5py.Group, episode: Episode) -> None:
    obs = group.create_group("obs")
    next_obs = group.create_group("next_obs")
    for name, frames in episode.obs.items():
        compression = "gzip" if name.endswith("_image") else None
        stacked = np.stack(frames)
        obs.create_dataset(name, data=stacked, compression=compression)
        after = np.concatenate([stacked[1:], episode.final_obs[name][None]])
        next_obs.create_dataset(name, data=after, compression=compression)
    group.create_dataset("actions", data=np.stack(episode.actions))
    group.create_dataset("rewards", data=np.asarray(episode.rewards, dtype=np.float64))
    dones = np.zeros(len(episode), dtype=np.int64)
    dones[-1] = 1
    group.create_dataset("dones", data=dones)
    group.create_dataset("states", data=np.stack(episode.states))
    group.attrs["num_samples"] = len(episode)
    if episode.model_file:  # robosuite's MJCF (robomimic replays states with it)
        group.attrs["model_file"] = episode.model_file
    group.attrs["seed"] = episode.seed


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
