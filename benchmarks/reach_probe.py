"""Why replanning at every step fails on a Meta-World task: per-step traces and probes.

    python benchmarks/reach_probe.py CKPT --task reach --probe receding-1 --n-test 20 [--json OUT]

The loop is `sefa eval --env metaworld:TASK`'s (sefa_sim.rollouts.metaworld_episode: seeds from
100000, the policy's noise seeded per episode, Meta-World's 500 steps, success at any step),
with the executor's settings given as an execution spec (receding-1, ensemble-1,
coherent-1x16; `sefa_model.policy.execution.parse_spec`) and with these probes on top:

* `--offset D`: replan every --probe's steps but execute the chunk from index start + D
  (start = n_obs_steps - 1, the current frame): is the chunk's first action the weak one?
* `--history current`: the prediction sees the current frame in place of the ones before it
  (no motion between its frames; Meta-World's vector still holds the previous step's hand).

* `--clamp-obs`: every observation clipped to the demonstrations' range, per dimension (the
  range the policy's `limits` normalizer maps to [-1, 1]).
* `--zero-action-dims 3`: these action dimensions executed as 0 whatever was predicted.

Each episode keeps, per step, the hand's distance to the goal and the action executed, so
that a failure can be told apart: stalled near the goal, oscillating, or never approaching.
Printed: the success rate, and over the failed episodes the median closest distance, the
median distance at the end, and the mean |action| over their last 100 steps.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

HAND, GOAL = slice(0, 3), slice(36, 39)  # Meta-World's 39-value observation


class Probe:
    """An executor wrapper: `offset` shifts which predicted action runs, `history` ("current")
    what a decision sees, `clamp` ({key: (lo, hi)}) clips the observations, `zero_dims` holds
    action dimensions at 0."""

    def __init__(self, executor, offset: int = 0, history: str = "real",
                 clamp: dict | None = None, zero_dims: tuple[int, ...] = ()):
        self.ex, self.offset, self.history = executor, offset, history
        self.clamp, self.zero_dims = clamp or {}, list(zero_dims)
        self.frames: list[dict] = []

    def reset(self, seed):
        self.frames = []
        self.ex.reset(seed)

    def action(self, frame):
        frame = {k: np.clip(v, *self.clamp[k]).astype(v.dtype) if k in self.clamp else v
                 for k, v in frame.items()}
        self.frames.append(frame)
        ex = self.ex
        if self.history == "current" and ex.steps_to_decision == 0 and len(self.frames) > 1:
            # the decision sees n_obs_steps copies of the current frame: no motion between them
            ex.history.extend([frame] * ex.shape.n_obs_steps)
        out = ex.action(frame)
        if self.offset:
            i = ex.shape.start + (ex.t - 1 - ex.plan_t) + self.offset
            out = np.asarray(ex.plan[min(i, len(ex.plan) - 1)], np.float32)
        if self.zero_dims:
            out = out.copy()
            out[self.zero_dims] = 0.0
        return out


def demo_ranges(policy) -> dict:
    """Per observation key, the (lo, hi) the limits normalizer maps to [-1, 1]: x_n = x * scale
    + offset, so x = (x_n - offset) / scale."""
    out = {}
    for key in policy.cfg.shape_meta.obs:
        a = policy.normalizer.params[key]
        lo, hi = (-1 - a.offset) / a.scale, (1 - a.offset) / a.scale
        out[key] = (np.minimum(lo, hi), np.maximum(lo, hi))
    return out


def episode(probe: Probe, keys, task: str, seed: int) -> dict:
    from sefa_sim.metaworld import make_env
    from sefa_sim.rollouts import metaworld_observation

    env = make_env(task, seed)
    try:
        probe.reset(seed)
        raw, _ = env.reset()
        dist, acts, success = [], [], False
        for _ in range(env.max_path_length):
            dist.append(float(np.linalg.norm(raw[HAND] - raw[GOAL])))
            action = probe.action(metaworld_observation(raw, keys))
            acts.append(np.clip(action, -1, 1).tolist())
            raw, _, _, truncated, info = env.step(np.clip(action, -1, 1))
            if info["success"]:
                success = True
                break
            if truncated:
                break
        return {"seed": seed, "success": success, "steps": len(dist), "dist": dist,
                "actions": acts}
    finally:
        env.close()


def summary(rows: list[dict]) -> dict:
    failed = [r for r in rows if not r["success"]]
    out = {"episodes": len(rows), "success_rate": float(np.mean([r["success"] for r in rows])),
           "median_steps_success": float(np.median([r["steps"] for r in rows if r["success"]]))
           if len(failed) < len(rows) else None}
    if failed:
        out["failed_median_closest"] = float(np.median([min(r["dist"]) for r in failed]))
        out["failed_median_final"] = float(np.median([r["dist"][-1] for r in failed]))
        out["failed_mean_abs_action_last100"] = float(np.mean(
            [np.abs(np.asarray(r["actions"][-100:])[:, :3]).mean() for r in failed]))
    return out


def main() -> None:
    from sefa_model.policy.artifact import Policy
    from sefa_model.policy.execution import Executor, parse_spec

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("checkpoint")
    ap.add_argument("--task", default="reach")
    ap.add_argument("--probe", default="receding-1", help="an execution spec (receding-1, ...)")
    ap.add_argument("--offset", type=int, default=0)
    ap.add_argument("--history", choices=("real", "current"), default="real")
    ap.add_argument("--clamp-obs", action="store_true")
    ap.add_argument("--zero-action-dims", type=int, nargs="*", default=[])
    ap.add_argument("--solver", default=None)
    ap.add_argument("--steps", type=int, default=None)
    ap.add_argument("--n-test", type=int, default=20)
    ap.add_argument("--start-seed", type=int, default=100000)
    ap.add_argument("--json", default=None, help="write every episode (traces included) here")
    a = ap.parse_args()
    torch.set_num_threads(1)
    policy = Policy.load(a.checkpoint, device="cpu")
    n = policy.cfg.policy.n_action_steps
    settings = parse_spec(a.probe).resolved(n)
    executor = Executor.for_policy(policy, settings, solver=a.solver, steps=a.steps)
    probe = Probe(executor, a.offset, a.history, demo_ranges(policy) if a.clamp_obs else None,
                  tuple(a.zero_action_dims))
    rows = [episode(probe, policy.cfg.shape_meta.obs, a.task, s)
            for s in range(a.start_seed, a.start_seed + a.n_test)]
    result = {"checkpoint": str(a.checkpoint), "task": a.task, "execution": settings.label,
              "offset": a.offset, "history": a.history, "clamp_obs": a.clamp_obs,
              "zero_action_dims": a.zero_action_dims, "solver": a.solver, "steps": a.steps,
              "seeds": [a.start_seed, a.start_seed + a.n_test - 1], **summary(rows)}
    print(json.dumps(result))
    if a.json:
        Path(a.json).write_text(json.dumps({**result, "per_seed": rows}))


if __name__ == "__main__":
    main()
