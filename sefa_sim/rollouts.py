"""Closed-loop evaluation of a policy in simulation, reported the way the field reports it.

Push-T (Diffusion Policy's protocol): test seeds 100000, 100001, ...; per episode the score is
the best reward min(coverage / 0.95, 1) reached; success is coverage > 0.95. The result is an
`eval_log.json` with the mean and the per-seed values.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np
import torch

from sefa_model.policy import Policy


def pusht_policy_fn(policy: Policy, solver: str | None = None, steps: int | None = None,
                    seed: int = 0):
    """Observation history {keypoint: (To, 9, 2), state: (To, 5)} -> (n_action_steps, 2)."""
    gen = torch.Generator().manual_seed(seed)

    def act(history: dict) -> np.ndarray:
        out = policy.predict_action(history, solver=solver, steps=steps, generator=gen)
        return out.action[0].cpu().numpy()
    return act


def evaluate_pusht(checkpoint: str | Path, *, n_test: int = 50, start_seed: int = 100000,
                   max_steps: int = 300, solver: str | None = None, steps: int | None = None,
                   out: Path | None = None, progress=lambda done, total: None) -> dict:
    from sefa_sim.pusht import FIRST_TEST_SEED, PushTEnv, rollout

    policy = Policy.load(checkpoint)
    if not set(policy.cfg.shape_meta.obs) <= {"keypoint", "state"}:
        from sefa_data.errors import SefaInputError

        raise SefaInputError("Push-T rollouts provide the observations keypoint and state; the "
                             f"policy needs {', '.join(policy.cfg.shape_meta.obs)}",
                             file=str(checkpoint))
    env = PushTEnv()
    p = policy.cfg.policy
    per_seed = []
    started = time.perf_counter()
    for i in range(n_test):
        seed = start_seed + i
        result = rollout(pusht_policy_fn(policy, solver, steps, seed), seed, max_steps=max_steps,
                         n_obs_steps=p.n_obs_steps, n_action_steps=p.n_action_steps, env=env)
        per_seed.append({k: result[k] for k in ("seed", "score", "max_coverage", "success", "steps")})
        progress(i + 1, n_test)
    log = {
        "env": "pusht", "checkpoint": policy.path, "kind": policy.kind,
        "solver": solver or policy.cfg.flow.solver, "test_start_seed": start_seed,
        "n_test": n_test, "max_steps": max_steps, "dp_seed_convention": start_seed == FIRST_TEST_SEED,
        "test/mean_score": float(np.mean([r["score"] for r in per_seed])),
        "test/success_rate": float(np.mean([r["success"] for r in per_seed])),
        "seconds": time.perf_counter() - started,
        "per_seed": per_seed,
    }
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        tmp = out / "eval_log.json.tmp"
        tmp.write_text(json.dumps(log, indent=2))
        os.replace(tmp, out / "eval_log.json")
    return log
