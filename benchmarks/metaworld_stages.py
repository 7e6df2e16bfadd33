"""Where a Meta-World episode fails: the stages Meta-World's own `info` reports, per episode.

    python benchmarks/metaworld_stages.py CKPT --task stick-pull [--n-test 50] [--solver euler --steps 1]

The same closed loop as `sefa eval --env metaworld:TASK` (sefa_sim.rollouts.metaworld_episode:
its seeds from 100000, the checkpoint's sampler, Meta-World's 500 steps, success at any step),
keeping for each episode whether the hand was ever near the object (`near_object`), whether the
object was ever grasped (`grasp_success`) and the closest the object came to its target
(`obj_to_target`). Printed: the success rate and, over the failed episodes, how many never
reached, never grasped, or grasped and still missed, with the median closest distance. `--json`
writes every episode.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch


def episode(policy, task: str, seed: int, solver, steps) -> dict:
    """One episode of `sefa eval`'s loop (metaworld_episode, Meta-World's own step limit),
    with the stages of each step's `info` kept."""
    from sefa_model.policy.execution import Executor
    from sefa_sim.rollouts import metaworld_episode

    seen = {"near_object": False, "grasped": False, "closest_obj_to_target": float("inf")}

    def watch(info: dict) -> None:
        seen["near_object"] |= bool(info.get("near_object", 0))
        seen["grasped"] |= bool(info.get("grasp_success", 0))
        seen["closest_obj_to_target"] = min(seen["closest_obj_to_target"],
                                            float(info.get("obj_to_target", np.inf)))

    executor = Executor.for_policy(policy, solver=solver, steps=steps)
    result = metaworld_episode(executor, policy.cfg.shape_meta.obs, task, seed, 10**9, watch)
    return {"seed": seed, "success": result["success"], "steps": result["steps"], **seen}


def summary(rows: list[dict]) -> dict:
    failed = [r for r in rows if not r["success"]]
    return {"episodes": len(rows), "success_rate": float(np.mean([r["success"] for r in rows])),
            "failed": len(failed),
            # a grasp counts as having been near, whatever near_object said
            "failed_never_near": sum(not r["near_object"] and not r["grasped"] for r in failed),
            "failed_near_never_grasped": sum(r["near_object"] and not r["grasped"] for r in failed),
            "failed_grasped": sum(r["grasped"] for r in failed),
            "failed_median_closest": float(np.median([r["closest_obj_to_target"] for r in failed]))
            if failed else None}


def main() -> None:
    from sefa_model.policy.artifact import Policy

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("checkpoint")
    ap.add_argument("--task", required=True)
    ap.add_argument("--n-test", type=int, default=50)
    ap.add_argument("--solver", default=None)
    ap.add_argument("--steps", type=int, default=None)
    ap.add_argument("--json", default=None, help="write every episode here")
    a = ap.parse_args()
    torch.set_num_threads(1)
    policy = Policy.load(a.checkpoint, device="cpu")
    rows = [episode(policy, a.task, seed, a.solver, a.steps)
            for seed in range(100000, 100000 + a.n_test)]
    result = {"checkpoint": str(a.checkpoint), "task": a.task, "solver": a.solver, "steps": a.steps,
              **summary(rows)}
    print(json.dumps(result))
    if a.json:
        Path(a.json).write_text(json.dumps({**result, "per_seed": rows}, indent=1))


if __name__ == "__main__":
    main()
