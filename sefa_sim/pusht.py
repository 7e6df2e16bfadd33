"""Push-T simulation in the conventions of Diffusion Policy's training store.

The store (``pusht_cchi_v7_replay.zarr``) holds ``state`` = agent x, y, block x, y, angle and
``keypoint`` = 9 points fixed in the block's own frame. gym-pusht simulates the same physics but
observes the T's 8 corners instead, so this module

- recovers the store's 9 local points (`fit_local_keypoints`) and places them by a block pose
  (`keypoints_from_pose`);
- wraps gym-pusht as `PushTEnv`, whose observations are ``{"keypoint": (9, 2), "state": (5,)}``
  in the store's conventions, plus ``"img"`` (96, 96, 3) uint8 for image policies, with
  Diffusion Policy's seeding and state placement;
- checks the adapter against real demonstrations (`replay_check`) and its camera image against
  the stored frames (`render_check`);
- runs a policy's executor for one seed (`episode`; a chunk function: `rollout`).

Pose convention (found empirically, see `fit_local_keypoints`): a keypoint is
``p + R(angle) @ local`` with ``R`` the ordinary rotation matrix in pixel coordinates, which is
also pymunk's ``Body.local_to_world``; the opposite sign leaves errors over 100 px.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

# Fitted once from the whole store with `fit_local_keypoints` (inlier frames, see there); kept
# here so that evaluation needs no store. tests/sefa_sim_tests/test_pusht_env.py re-fits and compares.
LOCAL_KEYPOINTS = np.array([
    [9.2697, 90.0411],
    [-60.9834, -1.1867],
    [60.9128, -1.3932],
    [-0.2705, 25.5437],
    [-14.0650, 122.8159],
    [39.0027, 32.8575],
    [-39.9664, 32.7297],
    [-16.8244, 62.8632],
    [23.5415, -1.7002],
])

# gym-pusht's own keypoint observation (`environment_state`, LeRobot's
# `observation.environment_state`): the vertices of the T's two rectangles in the block's frame,
# in the order pymunk returns them (gym-pusht's `get_keypoints`). Placed by the same pose as
# LOCAL_KEYPOINTS; tests/sefa_sim_tests/test_pusht_env.py checks them against gym-pusht.
GYM_PUSHT_CORNERS = np.array([
    [-60.0, 0.0], [60.0, 0.0], [60.0, 30.0], [-60.0, 30.0],
    [-15.0, 30.0], [15.0, 30.0], [15.0, 120.0], [-15.0, 120.0],
])

SUCCESS_COVERAGE = 0.95   # gym-pusht's and Diffusion Policy's success threshold
FIRST_TEST_SEED = 100_000  # Diffusion Policy evaluates on seeds 100000, 100001, ...

IMAGE_KEY = "img"  # the store's camera key, 96 x 96 RGB as Diffusion Policy renders it
# the agent's position alone, state[:2]: gym-pusht's name for it (LeRobot's `observation.state`)
AGENT_POS_KEY = "agent_pos"
OBS_KEYS = ("keypoint", "state", AGENT_POS_KEY, IMAGE_KEY)
# the simulator's names -> the policy's keys of a store of LeRobot's Push-T dataset (lerobot/pusht:
# `observation.image` 96 x 96 RGB, `observation.state` the agent's position): applied when a
# policy's keys are exactly these and no other map is given
LEROBOT_PUSHT_NAMES = {IMAGE_KEY: "observation.image", AGENT_POS_KEY: "observation.state"}

PolicyFn = Callable[[dict[str, np.ndarray]], np.ndarray]


# ----------------------------------------------------------------------------- keypoint geometry

def rotation_matrices(angle: np.ndarray) -> np.ndarray:
    """(...,) angles -> (..., 2, 2) rotation matrices."""
    c, s = np.cos(angle), np.sin(angle)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def keypoints_from_pose(block_pose: np.ndarray, local: np.ndarray = LOCAL_KEYPOINTS) -> np.ndarray:
    """(..., 3) block poses (x, y, angle) -> (..., K, 2) world keypoints of (K, 2) local points."""
    pose = np.asarray(block_pose, dtype=np.float64)
    rot = rotation_matrices(pose[..., 2])
    return np.einsum("...ij,kj->...ki", rot, np.asarray(local, np.float64)) + pose[..., None, :2]


def affine_weights(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(S, 2) and (K, 2) points of one rigid body's frame -> (K, S) weights W, each row summing
    to 1, with W @ source = target. A rigid motion (or any affine map) commutes with such
    combinations, so W @ (the S points placed by a pose) = the K points placed by that pose:
    gym-pusht's 8 corners give the store's 9 keypoints without solving for the pose. Of the
    weights that do this, the smallest (least squares), which amplify noise the least."""
    source, target = np.asarray(source, np.float64), np.asarray(target, np.float64)
    lhs = np.vstack([source.T, np.ones(len(source))])             # (3, S)
    rhs = np.vstack([target.T, np.ones(len(target))])             # (3, K)
    weights, *_ = np.linalg.lstsq(lhs, rhs, rcond=None)           # (S, K)
    if not np.allclose(lhs @ weights, rhs, atol=1e-9):
        raise ValueError("the source points span no plane: no affine weights reach the target")
    return weights.T


def keypoint_errors(block_pose: np.ndarray, keypoint: np.ndarray,
                    local: np.ndarray = LOCAL_KEYPOINTS) -> np.ndarray:
    """(N, 3), (N, K, 2) -> (N,): per frame, the largest point distance in pixels."""
    diff = keypoints_from_pose(block_pose, local) - np.asarray(keypoint, np.float64)
    return np.linalg.norm(diff, axis=-1).max(axis=-1)


def _local_per_frame(block_pose: np.ndarray, keypoint: np.ndarray, angle_sign: float) -> np.ndarray:
    """Each frame's keypoints brought back into the block frame: R^T (k - p)."""
    rot = rotation_matrices(angle_sign * block_pose[:, 2])
    return np.einsum("nji,nkj->nki", rot, keypoint - block_pose[:, None, :2])


def fit_local_keypoints(state: np.ndarray, keypoint: np.ndarray, angle_sign: float = 1.0,
                        inlier_px: float = 0.1, rounds: int = 3) -> np.ndarray:
    """(N, 5) states, (N, K, 2) keypoints -> (K, 2) points in the block frame.

    With the rotation known per frame, the least-squares local points are the mean of the frames'
    back-rotated points. About 0.5 % of the store's frames disagree with their own state by up to
    ~2 px (mostly an episode's first frames, the error halving each step: state and keypoints
    were apparently sampled at slightly different instants while the block moved), so the fit is
    repeated on the frames within `inlier_px` of the previous fit to keep them from biasing it.
    `angle_sign=-1` exists only to show that the other rotation convention does not fit.
    """
    pose = np.asarray(state, np.float64)[:, 2:5]
    kp = np.asarray(keypoint, np.float64)
    per_frame = _local_per_frame(pose, kp, angle_sign)
    signed_pose = pose * np.array([1.0, 1.0, angle_sign])
    local = np.median(per_frame, axis=0)  # robust start, the outliers pull a mean
    for _ in range(rounds):
        inliers = keypoint_errors(signed_pose, kp, local) < inlier_px
        if not inliers.any():
            break
        local = per_frame[inliers].mean(axis=0)
    return local


# ----------------------------------------------------------------------------- the store

@dataclass(frozen=True)
class PushTDemos:
    """The store's arrays needed here, read into memory (25,650 frames: a few MB)."""

    state: np.ndarray         # (N, 5) float64
    keypoint: np.ndarray      # (N, 9, 2) float64
    action: np.ndarray        # (N, 2) float64
    episode_ends: np.ndarray  # (E,) int

    def episode(self, index: int) -> slice:
        start = 0 if index == 0 else int(self.episode_ends[index - 1])
        return slice(start, int(self.episode_ends[index]))


def load_demos(store: str | Path | Any) -> PushTDemos:
    """Read a Diffusion-Policy ReplayBuffer store (path, or an opened zarr group)."""
    import zarr

    root = zarr.open_group(str(store), mode="r") if isinstance(store, (str, Path)) else store
    data = root["data"]
    return PushTDemos(
        state=np.asarray(data["state"][:], np.float64),
        keypoint=np.asarray(data["keypoint"][:], np.float64),
        action=np.asarray(data["action"][:], np.float64),
        episode_ends=np.asarray(root["meta"]["episode_ends"][:], np.int64),
    )


# ----------------------------------------------------------------------------- environment

def dp_initial_state(seed: int) -> np.ndarray:
    """Diffusion Policy's initial state for a seed (its legacy RandomState draw, in its order).

    gym-pusht draws from a different generator, so its seed N is another scene; drawing like
    Diffusion Policy makes test seeds 100000+ the same scenes its papers were scored on.
    """
    rs = np.random.RandomState(seed=seed)
    return np.array([
        rs.randint(50, 450), rs.randint(50, 450),
        rs.randint(100, 400), rs.randint(100, 400),
        rs.randn() * 2 * np.pi - np.pi,
    ], dtype=np.float64)


class PushTEnv:
    """gym-pusht with observations and placement in the store's conventions.

    obs = {"keypoint": (9, 2) store keypoints from the block pose, "state": (5,) agent x, y,
    block x, y, angle in [0, 2 pi)}. `step` returns (obs, reward, done, info) where reward is
    gym-pusht's min(coverage / 0.95, 1), done means coverage > 0.95, and info["coverage"] is the
    raw goal-area coverage.
    """

    def __init__(self, local_keypoints: np.ndarray = LOCAL_KEYPOINTS) -> None:
        import gym_pusht  # noqa: F401  (registers gym_pusht/PushT-v0)
        import gymnasium

        # The unwrapped env: our caller owns the step limit, and the passive checker only warns.
        self._env = gymnasium.make("gym_pusht/PushT-v0", obs_type="state",
                                   render_mode="rgb_array").unwrapped
        self.local_keypoints = np.asarray(local_keypoints, np.float64)
        # gym-pusht's coverage, over the T's two boxes in a fixed order: its own iterates
        # pymunk's set of shapes, whose order follows the objects' addresses, and shapely's
        # intersection area changes in the last bits with the order (0.21852179689450896 or
        # ...899 for one pose, by process), so a score was not reproducible across processes.
        # Its step reads the reward, the success and info["coverage"] from this method.
        self._env._get_coverage = self._ordered_coverage
        self._env.reset(seed=0)  # builds the pymunk space so set_state works before reset

    # -- placement

    def reset(self, seed: int) -> dict[str, np.ndarray]:
        """Diffusion Policy's scene for `seed` (see `dp_initial_state`)."""
        self._env.reset(seed=seed)
        return self.set_state(dp_initial_state(seed))

    def set_state(self, state: np.ndarray) -> dict[str, np.ndarray]:
        """Place agent and block exactly at `state` (5,), at rest, in a fresh physics space.

        gym-pusht's own reset_to_state sets the block position before its angle; pymunk turns a
        body about its centre of gravity, which is not the T's origin, so that order moves the
        block (90 px for the first frame of the store's episode 0). Diffusion Policy's env
        (legacy=False) sets the angle first, so the reported pose equals the requested one; so do
        we. With this placement, replaying a demo's actions open loop from its first state tracks
        the stored agent within 1e-4 px and the block within 0.25 px over the whole store.
        """
        env = self._env
        env._setup()  # fresh space: no velocities or contact caches from a previous scene
        state = np.asarray(state, np.float64)
        env.agent.position = state[:2].tolist()
        env.block.angle = float(state[4])
        env.block.position = state[2:4].tolist()
        env.space.step(env.dt)  # as both upstream envs do, so the placement takes effect
        return self.observation()

    # -- stepping

    def step(self, action: np.ndarray) -> tuple[dict[str, np.ndarray], float, bool, dict]:
        _, reward, terminated, _, info = self._env.step(np.asarray(action, np.float64))
        return self.observation(), float(reward), bool(terminated), info

    # -- reading

    @property
    def block_pose(self) -> np.ndarray:
        """(3,) block x, y, angle as pymunk reports it (angle not wrapped)."""
        block = self._env.block
        return np.array([block.position.x, block.position.y, block.angle], np.float64)

    @property
    def coverage(self) -> float:
        return float(self._env._get_coverage())

    def _ordered_coverage(self) -> float:
        """gym-pusht's `_get_coverage` with the block's shapes sorted by their vertices."""
        from gym_pusht.envs.pusht import pymunk_to_shapely

        env = self._env
        shapes = sorted(env.block.shapes, key=lambda s: [tuple(v) for v in s.get_vertices()])
        goal = pymunk_to_shapely(env.get_goal_pose_body(env.goal_pose), shapes)
        block = pymunk_to_shapely(env.block, shapes)
        return goal.intersection(block).area / goal.area

    def observation(self) -> dict[str, np.ndarray]:
        pose = self.block_pose
        agent = self._env.agent.position
        state = np.array([agent.x, agent.y, pose[0], pose[1], pose[2] % (2 * np.pi)])
        return {"keypoint": keypoints_from_pose(pose, self.local_keypoints), "state": state,
                AGENT_POS_KEY: state[:2].copy()}

    def image(self) -> np.ndarray:
        """(96, 96, 3) uint8: the scene as Diffusion Policy's image env observes it (goal,
        block and agent drawn at 512 px, resized with OpenCV), without the action marker.
        About 12 ms on one core, so rollouts render only the frames a policy will see."""
        return self._env._render(visualize=False)


# ----------------------------------------------------------------------------- checks on real demos

def _state_replay_errors(env: PushTEnv, demos: PushTDemos, frames: slice) -> np.ndarray:
    """Per frame: place the stored state, compare keypoints from the env's pose with the store."""
    errors = []
    for t in range(frames.start, frames.stop):
        obs = env.set_state(demos.state[t])
        errors.append(np.linalg.norm(obs["keypoint"] - demos.keypoint[t], axis=-1).max())
    return np.asarray(errors)


def _action_replay_drift(env: PushTEnv, demos: PushTDemos, frames: slice) -> dict[str, float]:
    """Open loop from the first stored state: action t should lead to stored state t + 1.

    Not required to be small (pymunk's version differs from the recording's), but measured on
    the whole store it is: agent < 1e-4 px, block < 0.25 px.
    """
    env.set_state(demos.state[frames.start])
    block_err, agent_err, kp_err = [], [], []
    for t in range(frames.start, frames.stop - 1):
        obs, _, _, _ = env.step(demos.action[t])
        target = demos.state[t + 1]
        agent_err.append(np.linalg.norm(obs["state"][:2] - target[:2]))
        block_err.append(np.linalg.norm(obs["state"][2:4] - target[2:4]))
        kp_err.append(np.linalg.norm(obs["keypoint"] - demos.keypoint[t + 1], axis=-1).max())
    return {
        "agent_px_mean": float(np.mean(agent_err)), "agent_px_max": float(np.max(agent_err)),
        "block_px_final": float(block_err[-1]), "block_px_max": float(np.max(block_err)),
        "keypoint_px_final": float(kp_err[-1]), "keypoint_px_max": float(np.max(kp_err)),
    }


def replay_check(store: str | Path | Any | PushTDemos, episodes: Sequence[int] = (0, 1, 2),
                 env: PushTEnv | None = None) -> dict[str, Any]:
    """State replay (must be sub-pixel) and open-loop action replay (drift, informative) per demo.

    Returns {"state_replay": {"keypoint_px_max", "keypoint_px_mean", "frames"},
             "action_replay": {episode: drift dict}, "episodes": [...]}.
    """
    demos = store if isinstance(store, PushTDemos) else load_demos(store)
    env = env or PushTEnv()
    state_errors, drift = [], {}
    for episode in episodes:
        frames = demos.episode(episode)
        state_errors.append(_state_replay_errors(env, demos, frames))
        drift[int(episode)] = _action_replay_drift(env, demos, frames)
    errors = np.concatenate(state_errors)
    return {
        "episodes": [int(e) for e in episodes],
        "state_replay": {"keypoint_px_max": float(errors.max()),
                         "keypoint_px_mean": float(errors.mean()), "frames": int(errors.size)},
        "action_replay": drift,
    }


# ----------------------------------------------------------------------------- policy rollout

def render_check(store: str | Path | Any, frames: Sequence[int] | None = None,
                 env: PushTEnv | None = None) -> dict[str, Any]:
    """Place stored states, render, and compare with the stored camera frames (``data/img``,
    float 0..255 in Diffusion Policy's store). Returns the mean absolute pixel difference (in
    0..255 units), its largest per-frame value, the fraction of pixels that differ at all and by
    more than 32, and the worst frame."""
    import zarr

    root = zarr.open_group(str(store), mode="r") if isinstance(store, (str, Path)) else store
    images, states = root["data"]["img"], root["data"]["state"]
    frames = list(frames) if frames is not None else list(np.linspace(0, states.shape[0] - 1, 200).astype(int))
    env = env or PushTEnv()
    mean_abs, differ, differ32 = [], [], []
    for t in frames:
        env.set_state(states[t])
        diff = np.abs(env.image().astype(np.float32) - np.asarray(images[t], np.float32))
        mean_abs.append(float(diff.mean()))
        differ.append(float((diff > 0).mean()))
        differ32.append(float((diff > 32).mean()))
    worst = int(np.argmax(mean_abs))
    return {"frames": len(frames), "mean_abs": float(np.mean(mean_abs)),
            "max_frame_mean_abs": mean_abs[worst], "worst_frame": int(frames[worst]),
            "fraction_differing": float(np.mean(differ)),
            "fraction_differing_over_32": float(np.mean(differ32))}


def policy_names(policy_keys: Sequence[str], key_map: Mapping[str, str] | None = None
                 ) -> tuple[dict[str, str], str | None]:
    """{policy key: the simulator's observation that feeds it}, and a note when LeRobot's
    Push-T names were recognised. `key_map` is `sefa eval --key-map`'s NAME=KEY pairs (the
    simulator's NAME feeds the policy's KEY, as `sefa serve --key-map` maps a client's names);
    a policy key it does not name is fed by the simulator's observation of the same name.
    SefaInputError (one line, with the way out) when a key has no source."""
    from sefa_data.errors import SefaInputError

    note = None
    if not key_map and set(policy_keys) == set(LEROBOT_PUSHT_NAMES.values()):
        key_map, note = LEROBOT_PUSHT_NAMES, ("Push-T's " + ", ".join(
            f"{n} as {k}" for n, k in LEROBOT_PUSHT_NAMES.items()) + " (LeRobot's names)")
    key_map = dict(key_map or {})
    for name, key in key_map.items():
        if name not in OBS_KEYS:
            raise SefaInputError(f"'{name}={key}': Push-T has no observation '{name}' "
                                 f"(it has: {', '.join(OBS_KEYS)})", key="--key-map")
        if key and key not in policy_keys:
            raise SefaInputError(f"'{name}={key}': the policy has no observation '{key}' (it "
                                 f"takes: {', '.join(policy_keys)})", key="--key-map")
    feeds = {key: name for name, key in key_map.items() if key}
    for key in policy_keys:
        if key not in feeds and key in OBS_KEYS and key not in key_map:
            feeds[key] = key
    missing = [k for k in policy_keys if k not in feeds]
    if missing:
        raise SefaInputError(
            f"Push-T rollouts provide the observations {', '.join(OBS_KEYS)} ({IMAGE_KEY} a 96x96 "
            f"camera image, {AGENT_POS_KEY} the agent's position, state[:2]); nothing feeds the "
            f"policy's {', '.join(missing)}: map one with --key-map NAME=KEY, e.g. "
            f"`sefa eval --env pusht --key-map {AGENT_POS_KEY}={missing[0]}`", key="--key-map")
    return {k: feeds[k] for k in policy_keys}, note


def episode(executor, seed: int, max_steps: int = 300, env: PushTEnv | None = None,
            images: bool = False, feeds: Mapping[str, str] | None = None) -> dict[str, Any]:
    """One Diffusion-Policy scene, closed loop: the executor (sefa_model/policy/execution.py,
    reset with the seed, so its noise is the episode's) gets the newest frame every step, under
    the policy's keys (`feeds`: policy key -> the simulator's name; default the simulator's
    own names), and answers the action (the agent's absolute target). The episode ends on
    success or after max_steps env steps. With `images` the camera frame is rendered only for
    the steps a prediction will see (the others would cost 12 ms each and be dropped from the
    history unseen).

    score is Diffusion Policy's test score: the best reward, min(coverage / 0.95, 1), reached;
    max_coverage is the raw best coverage; success means coverage > 0.95 was reached.
    """
    env = env or PushTEnv()
    executor.reset(seed)
    obs = env.reset(seed)
    if images:
        obs[IMAGE_KEY] = env.image()
    names = dict(feeds) if feeds is not None else {k: k for k in obs}
    best_reward, best_coverage, steps, done = 0.0, env.coverage, 0, False
    started = time.perf_counter()
    while not done and steps < max_steps:
        action = executor.action({k: obs[n] for k, n in names.items() if n in obs})
        obs, reward, done, info = env.step(np.asarray(action, np.float64))
        if images and executor.steps_to_decision < executor.shape.n_obs_steps:
            obs[IMAGE_KEY] = env.image()
        best_reward = max(best_reward, reward)
        best_coverage = max(best_coverage, float(info["coverage"]))
        steps += 1
    return {
        "seed": int(seed), "score": best_reward, "max_coverage": best_coverage,
        "success": best_coverage > SUCCESS_COVERAGE, "steps": steps,
        "seconds": time.perf_counter() - started,
    }


def rollout(policy_fn: PolicyFn, seed: int, max_steps: int = 300, n_obs_steps: int = 2,
            n_action_steps: int = 8, env: PushTEnv | None = None,
            images: bool = False) -> dict[str, Any]:
    """`episode` for a chunk function: policy_fn gets {"keypoint": (To, 9, 2), "state": (To,
    5)}, oldest first (the first observation repeated to fill the window at the start), plus
    "img" (To, 96, 96, 3) uint8 with `images`, and returns (>= n_action_steps, 2) absolute agent
    targets, of which the first n_action_steps are executed (receding horizon)."""
    from sefa_model.policy.execution import ChunkShape, Executor, default_settings

    shape = ChunkShape(n_obs_steps, n_action_steps, n_obs_steps - 1 + n_action_steps, 2)

    def chunk(obs: dict[str, np.ndarray], noise: np.ndarray, generator) -> np.ndarray:
        actions = np.asarray(policy_fn({k: v[0] for k, v in obs.items()}), np.float64)
        out = np.zeros((1, shape.horizon, 2))
        out[0, shape.start:] = actions[:n_action_steps]
        return out
    executor = Executor(default_settings(n_action_steps), chunk, shape)
    return episode(executor, seed, max_steps, env, images)
