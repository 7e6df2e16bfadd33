"""Meta-World (metaworld 3.1.1): its 50 tasks, their difficulty groups, scripted demonstrations
in the robomimic layout, and the task and observation conventions rollouts share.

Tasks are named as Meta-World names them without the version suffix (`reach`, `pick-place`);
`reach-v3` is accepted too. `metaworld:GROUP` names a difficulty group (easy, medium, hard,
very_hard) and `metaworld:all` every task.

The goal of an episode is fixed by its seed the way Meta-World's benchmarks fix one: Meta-World's
goal-observable env, built with `seed=s`, seeds NumPy's global generator with s, resets once to
draw the object and goal positions (`rand_vec`), then freezes them; `MT1(task, seed=s)` draws its
first goal the same way. So an episode depends on its seed alone, whatever ran before it, and the
scripted policies are deterministic functions of the observation.

Observations: Meta-World's 39-dim goal-observable state vector, stored whole as
`state_observation` (Meta-World's own name for it) and as the parts Meta-World's documentation
names (docs/benchmark/state_space.md): the hand position, how far apart the gripper fingers are,
the first and second object's position and quaternion (zeros where a task has one object), the
goal position. The vector's 18 middle entries repeat the previous step's first 18 (Meta-World's
frame stacking); they are not stored again as parts.
"""

from __future__ import annotations

import difflib
import json
import warnings
from typing import Any

import numpy as np

from sefa_data.errors import SefaInputError
from sefa_sim.demo_file import Episode, plan_target, record

# Meta-World's tasks by difficulty, as 3D Diffusion Policy groups them (Ze et al., "3D Diffusion
# Policy", RSS 2024, arXiv:2403.03954, appendix: Meta-World task difficulty, after Seo et al.,
# "Masked World Models for Visual Control", CoRL 2022): 28 easy, 11 medium, 6 hard, 5 very hard.
GROUPS: dict[str, tuple[str, ...]] = {
    "easy": (
        "button-press", "button-press-topdown", "button-press-topdown-wall", "button-press-wall",
        "coffee-button", "dial-turn", "door-close", "door-lock", "door-open", "door-unlock",
        "drawer-close", "drawer-open", "faucet-close", "faucet-open", "handle-press",
        "handle-press-side", "handle-pull", "handle-pull-side", "lever-pull", "plate-slide",
        "plate-slide-back", "plate-slide-back-side", "plate-slide-side", "reach", "reach-wall",
        "window-close", "window-open", "peg-unplug-side"),
    "medium": (
        "basketball", "bin-picking", "box-close", "coffee-pull", "coffee-push", "hammer",
        "peg-insert-side", "push-wall", "soccer", "sweep", "sweep-into"),
    "hard": ("assembly", "hand-insert", "pick-out-of-hole", "pick-place", "push", "push-back"),
    "very_hard": ("shelf-place", "disassemble", "stick-pull", "stick-push", "pick-place-wall"),
}
TASKS: tuple[str, ...] = tuple(t for group in GROUPS.values() for t in group)
ALL = "all"
VERSION_SUFFIX = "-v3"
MAX_PATH_LENGTH = 500  # Meta-World's episode length (SawyerXYZEnv.max_path_length)
# one action per env step of 5 MuJoCo steps of 2.5 ms (env.dt = 0.0125 s): recorded in the file
# (env_info.control_freq) so that `sefa ingest` knows the rate without --fps
CONTROL_FREQ = 80.0

# name -> slice of the 39-dim observation (docs/benchmark/state_space.md)
STATE_KEY = "state_observation"
PARTS: dict[str, slice] = {
    "hand_pos": slice(0, 3),
    "gripper_distance_apart": slice(3, 4),
    "obj_pos": slice(4, 7),
    "obj_quat": slice(7, 11),
    "obj2_pos": slice(11, 14),
    "obj2_quat": slice(14, 18),
    "goal_pos": slice(36, 39),
}
OBS_KEYS: tuple[str, ...] = (STATE_KEY, *PARTS)
STATE_DIM = 39


def group_of(task: str) -> str:
    return next(g for g, tasks in GROUPS.items() if task in tasks)


def resolve(spec: str, option: str = "--env") -> list[str]:
    """`reach`, `reach-v3`, a group or `all` -> the task names; anything else is one line that
    lists every valid name, the nearest first."""
    name = spec.strip().lower()
    if name == ALL:
        return list(TASKS)
    if name in GROUPS:
        return list(GROUPS[name])
    task = name.removesuffix(VERSION_SUFFIX)
    if task in TASKS:
        return [task]
    valid = [*GROUPS, ALL, *TASKS]
    nearest = sorted(valid, key=lambda v: -difflib.SequenceMatcher(None, task, v).ratio())
    raise SefaInputError(f"unknown Meta-World task or group '{spec}' (valid, nearest first: "
                         f"{', '.join(nearest)})", key=option)


def canonical(spec: str, option: str = "--env") -> str:
    """The name results use: a group or `all` as it is, a task without its version."""
    tasks = resolve(spec, option)
    name = spec.strip().lower()
    return name if name in GROUPS or name == ALL else tasks[0]


def make_env(task: str, seed: int) -> Any:
    """Meta-World's goal-observable env for `task`, its object and goal positions fixed by
    `seed` (see the module's docstring)."""
    from metaworld import ALL_V3_ENVIRONMENTS_GOAL_OBSERVABLE

    return ALL_V3_ENVIRONMENTS_GOAL_OBSERVABLE[f"{task}{VERSION_SUFFIX}-goal-observable"](seed=seed)


def expert(task: str) -> Any:
    from metaworld.policies import ENV_POLICY_MAP

    return ENV_POLICY_MAP[f"{task}{VERSION_SUFFIX}"]()


def split_obs(obs: np.ndarray) -> dict[str, np.ndarray]:
    """The stored observation: the whole vector and its named parts (float64, as Meta-World
    gives them)."""
    obs = np.asarray(obs, np.float64)
    if obs.shape != (STATE_DIM,):
        raise ValueError(f"a Meta-World observation has {STATE_DIM} entries, got {obs.shape}")
    return {STATE_KEY: obs.copy(), **{k: obs[s].copy() for k, s in PARTS.items()}}


def physics_state(env: Any) -> np.ndarray:
    """(time, qpos, qvel), as robosuite flattens a MuJoCo state (what `states` holds for Lift)."""
    return np.concatenate([[env.data.time], env.data.qpos, env.data.qvel])


def run_episode(task: str, seed: int, max_steps: int = MAX_PATH_LENGTH, policy: Any = None
                ) -> Episode:
    """One seeded scripted episode; it ends at the first step where info['success'] is set,
    or after max_steps (at most Meta-World's episode length)."""
    env = make_env(task, seed)
    policy = policy or expert(task)
    try:
        obs, _ = env.reset()
        episode = Episode(seed=seed, success=False)
        for _ in range(min(max_steps, env.max_path_length)):
            for name, value in split_obs(obs).items():
                episode.obs.setdefault(name, []).append(value)
            episode.states.append(physics_state(env))
            # the env clips actions to [-1, 1] itself; we store what it executed (and so the
            # scripted policies' warning that their gains exceed that range says nothing new)
            with warnings.catch_warnings():
                warnings.filterwarnings("ignore", message="Constant\\(s\\) may be too high")
                raw = policy.get_action(obs)
            action = np.clip(np.asarray(raw, np.float64), -1.0, 1.0)
            obs, reward, _, truncated, info = env.step(action)
            episode.actions.append(action)
            episode.rewards.append(float(reward))
            if info["success"]:
                episode.success = True
                break
            if truncated:
                break
        episode.final_obs = split_obs(obs)
        return episode
    finally:
        env.close()


def env_args(task: str, max_steps: int) -> dict[str, Any]:
    """The file's env_args. type 2 is robomimic's EnvType.GYM_TYPE (robomimic has no Meta-World
    type; its loader only reads these fields); env_kwargs is what rebuilds the env with
    gymnasium: gym.make('Meta-World/goal_observable', env_name=..., seed=<the demo's seed>)."""
    from importlib.metadata import version

    return {"env_name": "Meta-World/goal_observable", "env_version": version("metaworld"),
            "type": 2, "env_kwargs": {"env_name": f"{task}{VERSION_SUFFIX}",
                                      "max_episode_steps": max_steps},
            "task": task, "difficulty": group_of(task)}


def collect_metaworld(out_path, task: str, episodes: int, seed: int = 0,
                      max_steps: int = MAX_PATH_LENGTH, *, append: bool = False,
                      force: bool = False) -> dict[str, Any]:
    """Run `episodes` seeded scripted episodes (seed, seed+1, ...) of one task; write the
    successful ones (the same layout, options and summary as `collect_lift`)."""
    tasks = resolve(task)
    if len(tasks) != 1:
        raise SefaInputError(f"collect records one Meta-World task at a time, and '{task}' is a "
                             f"group of {len(tasks)}", key="--env")
    [task] = tasks
    target = plan_target(out_path, episodes, seed, append=append, force=force)
    policy = expert(task)
    summary = record(target, range(seed, seed + episodes),
                     lambda s: run_episode(task, s, max_steps, policy),
                     env_args(task, max_steps), env_info={"control_freq": CONTROL_FREQ})
    return {"task": task, **summary}


def main(argv: list[str] | None = None) -> int:
    import argparse

    parser = argparse.ArgumentParser(description="Scripted Meta-World demos -> robomimic HDF5")
    parser.add_argument("out")
    parser.add_argument("--task", required=True)
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    print(json.dumps(collect_metaworld(args.out, args.task, args.episodes, args.seed)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
