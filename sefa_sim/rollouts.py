"""Closed-loop evaluation of a policy in simulation, reported the way the field reports it.

Push-T (Diffusion Policy's protocol): test seeds 100000, 100001, ...; per episode the score is
the best reward min(coverage / 0.95, 1) reached; success is coverage > 0.95. robosuite Lift: the
success rate (the cube lifted at any step within `max_steps`), the same seeds. Meta-World
(its evaluation protocol): the success rate, an episode succeeding when info['success'] is set at
any step within Meta-World's 500 steps, each test seed fixing its own object and goal positions
(sefa_sim/metaworld.py), the same seeds from 100000 (demonstrations use seeds from 0). The result
is an `eval_log.json` with the mean and the per-seed values.

Every episode depends on its seed alone (the scene and the policy's noise generator are seeded
per episode), so under torchrun the seeds are split across ranks (seed i to rank i % N) and
rank 0 gathers the episodes and writes the log: the same per-seed results as one process.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from sefa_model.distributed import context
from sefa_data import atomic
from sefa_model.policy.artifact import Policy
from sefa_model.policy.execution import ExecutionSettings, Executor, load_choice
from sefa_model.progress import report
from sefa_model.policy.sampling import solver_label

# bid's weaker policy: (checkpoint, solver, steps), loaded beside the policy
Weak = tuple[str, "str | None", "int | None"]


def my_seeds(start_seed: int, n_test: int) -> list[int]:
    """This rank's test seeds."""
    return list(context().shard(range(start_seed, start_seed + n_test)))


def gathered(per_seed: list[dict]) -> list[dict] | None:
    """Every rank's episodes in seed order on rank 0; None on the other ranks."""
    parts = context().gather(per_seed)
    return None if parts is None else sorted((r for part in parts for r in part), key=lambda r: r["seed"])


def pusht_policy_fn(policy: Policy, solver: str | None = None, steps: int | None = None,
                    seed: int = 0, nfe: list[int] | None = None):
    """Observation history {keypoint: (To, 9, 2), state: (To, 5)} -> (n_action_steps, 2);
    each call's network evaluations are appended to `nfe` when given (for studies that drive
    the chunks themselves; evaluations run an `Executor`)."""
    gen = torch.Generator().manual_seed(seed)

    def act(history: dict) -> np.ndarray:
        out = policy.predict_action(history, solver=solver, steps=steps, generator=gen)
        if nfe is not None:
            nfe.append(int(out.nfe))
        return out.action[0].cpu().numpy()
    return act


def policy_executor(policy: Policy, execution: ExecutionSettings | None, solver: str | None,
                    steps: int | None, weak: Weak | None, nfe: list[int],
                    device: str = "auto") -> Executor:
    """The executor an evaluation runs: `execution`, else the one chosen for this policy at
    this sampler setting (sefa choose-execution), else receding over n_action_steps."""
    if execution is None:
        execution = load_choice(policy.path, solver_label(policy.cfg, solver, steps))
    weak_policy = None
    if weak is not None:
        weak_policy = (Policy.load(weak[0], device=device), weak[1], weak[2])
    return Executor.for_policy(policy, execution, solver=solver, steps=steps, weak=weak_policy,
                               nfe=nfe)


def execution_fields(executor: Executor) -> dict:
    """What every rollout log says of its execution, and what its decisions took here: the
    p50 and p99 of every decision's wall time (the policy's sampling and the execution's
    choice, not the simulator's step) and torch's threads, so that two evaluations' latencies
    compare (`sefa results`)."""
    seconds = np.asarray(executor.decision_seconds)
    timing = None
    if len(seconds):
        p50, p99 = np.percentile(seconds, [50, 99]) * 1e3
        timing = {"p50_ms": round(float(p50), 4), "p99_ms": round(float(p99), 4),
                  "decisions": len(seconds), "threads": torch.get_num_threads()}
    return {"execution": executor.settings.to_json(), "execution_label": executor.settings.label,
            "decision_ms": timing}


def started_rollouts(total: int) -> None:
    """Report 0 episodes done when the first starts: the rate (and ETA) then counts from
    here, where a first report after episode 1 counted that episode as taking no time (an
    ETA of 2:48 for a run that took 4:25)."""
    report("rollouts", 0, total)


def mean_nfe(calls: list[int]) -> float | int | None:
    """Network evaluations per predicted chunk over a rollout evaluation (an adaptive solver's
    vary; a fixed one's are one integer)."""
    if not calls:
        return None
    mean = float(np.mean(calls))
    return int(mean) if mean.is_integer() else round(mean, 2)


def _write_log(log: dict, out: Path | None) -> dict:
    if out is not None and context().is_main:
        atomic.write_json(out / "eval_log.json", log)
    return log


def lift_observation(obs: dict, policy_keys) -> dict[str, np.ndarray]:
    """robosuite's observation under the store's names (`observation.<robomimic key>`)."""
    from sefa_sim.collect import OBJECT_KEY

    out = {}
    for key in policy_keys:
        name = key.removeprefix("observation.")
        source = OBJECT_KEY[0] if name == OBJECT_KEY[1] else name
        if source not in obs:
            from sefa_data.errors import SefaInputError

            raise SefaInputError(f"the Lift environment has no observation '{source}' "
                                 f"(it has: {', '.join(sorted(obs))})", key=key)
        out[key] = np.asarray(obs[source], np.float32)
    return out


def evaluate_lift(checkpoint: str | Path, *, n_test: int = 50, start_seed: int = 100000,
                  max_steps: int = 200, solver: str | None = None, steps: int | None = None,
                  out: Path | None = None, device: str = "auto",
                  execution: ExecutionSettings | None = None, weak: Weak | None = None
                  ) -> dict | None:
    """The log on rank 0 (None on the other ranks under torchrun)."""
    from sefa_sim.collect import env_kwargs, make_env

    policy = Policy.load(checkpoint, device=device)
    env = make_env(env_kwargs())
    per_seed, nfe = [], []
    executor = policy_executor(policy, execution, solver, steps, weak, nfe, device)
    started = time.perf_counter()
    started_rollouts(len(my_seeds(start_seed, n_test)))
    for seed in my_seeds(start_seed, n_test):
        np.random.seed(seed)  # robosuite draws the scene from numpy's global generator
        executor.reset(seed)
        obs = lift_observation(env.reset(), policy.cfg.shape_meta.obs)
        success, t = False, 0
        while t < max_steps and not success:
            raw, _, _, _ = env.step(np.clip(executor.action(obs), -1, 1))
            obs = lift_observation(raw, policy.cfg.shape_meta.obs)
            t += 1
            success = bool(env._check_success())
        per_seed.append({"seed": seed, "success": success, "steps": t})
        report("rollouts", len(per_seed), len(my_seeds(start_seed, n_test)),
               success=f"{np.mean([r['success'] for r in per_seed]):.0%}")
    env.close()
    per_seed = gathered(per_seed)
    if per_seed is None:
        return None
    return _write_log({
        "env": "robosuite:Lift", "checkpoint": policy.path, "kind": policy.kind,
        "solver": solver_label(policy.cfg, solver, steps), "nfe": mean_nfe(nfe),
        **execution_fields(executor),
        "test_start_seed": start_seed, "n_test": n_test, "max_steps": max_steps,
        "test/mean_score": float(np.mean([r["success"] for r in per_seed])),
        "test/success_rate": float(np.mean([r["success"] for r in per_seed])),
        "seconds": time.perf_counter() - started, "per_seed": per_seed}, out)


def evaluate_pusht(checkpoint: str | Path, *, n_test: int = 50, start_seed: int = 100000,
                   max_steps: int = 300, solver: str | None = None, steps: int | None = None,
                   out: Path | None = None, progress=lambda done, total: None,
                   device: str = "auto", key_map: dict[str, str] | None = None,
                   log=lambda _: None, execution: ExecutionSettings | None = None,
                   weak: Weak | None = None) -> dict | None:
    """The log on rank 0 (None on the other ranks under torchrun). `key_map`: the simulator's
    observation names -> the policy's keys (sefa_sim/pusht.py:policy_names)."""
    from sefa_sim.pusht import FIRST_TEST_SEED, IMAGE_KEY, PushTEnv, episode, policy_names

    policy = Policy.load(checkpoint, device=device)
    meta = policy.cfg.shape_meta.obs
    feeds, note = policy_names(list(meta), key_map)
    if note:
        log(note)
    for key, name in feeds.items():
        if (name == IMAGE_KEY) != (meta[key].type == "rgb"):
            from sefa_data.errors import SefaInputError

            raise SefaInputError(f"Push-T's {name} is {'a 96x96 camera image' if name == IMAGE_KEY else 'low-dim'}"
                                 f"; the policy's {key} is {meta[key].type}", file=str(checkpoint))
    env = PushTEnv()
    per_seed, nfe = [], []
    executor = policy_executor(policy, execution, solver, steps, weak, nfe, device)
    started = time.perf_counter()
    seeds = my_seeds(start_seed, n_test)
    started_rollouts(len(seeds))
    for i, seed in enumerate(seeds):
        result = episode(executor, seed, max_steps=max_steps, env=env,
                         images=IMAGE_KEY in feeds.values(), feeds=feeds)
        per_seed.append({k: result[k] for k in ("seed", "score", "max_coverage", "success", "steps")})
        progress(i + 1, len(seeds))
        report("rollouts", i + 1, len(seeds), mean_score=float(np.mean([r["score"] for r in per_seed])),
               success=f"{np.mean([r['success'] for r in per_seed]):.0%}")
    per_seed = gathered(per_seed)
    if per_seed is None:
        return None
    record = {
        "env": "pusht", "checkpoint": policy.path, "kind": policy.kind,
        "solver": solver_label(policy.cfg, solver, steps), "nfe": mean_nfe(nfe),
        **execution_fields(executor),
        "test_start_seed": start_seed, "n_test": n_test, "max_steps": max_steps,
        "dp_seed_convention": start_seed == FIRST_TEST_SEED,
        "test/mean_score": float(np.mean([r["score"] for r in per_seed])),
        "test/success_rate": float(np.mean([r["success"] for r in per_seed])),
        "seconds": time.perf_counter() - started,
        "per_seed": per_seed,
    }
    if any(k != n for k, n in feeds.items()):  # which simulator observation fed which key
        record["key_map"] = {n: k for k, n in feeds.items()}
    return _write_log(record, out)


def metaworld_observation(obs: np.ndarray, policy_keys) -> dict[str, np.ndarray]:
    """Meta-World's 39-dim observation under the store's names (`observation.<part>`, the
    names `sefa collect --env metaworld:TASK` records)."""
    from sefa_sim.metaworld import OBS_KEYS, split_obs

    parts = split_obs(obs)
    out = {}
    for key in policy_keys:
        name = key.removeprefix("observation.")
        if name not in parts:
            from sefa_data.errors import SefaInputError

            raise SefaInputError(f"Meta-World has no observation '{name}' (it has: "
                                 f"{', '.join(OBS_KEYS)})", key=key)
        out[key] = parts[name].astype(np.float32)
    return out


def metaworld_episode(executor: Executor, keys, task: str, seed: int, max_steps: int,
                      watch: Callable[[dict], None] | None = None) -> dict:
    """One closed-loop episode on the seed's goal, the executor (of a policy reading `keys`)
    reset with the seed; success:
    info['success'] at any step (Meta-World's evaluation protocol). `watch` is given every
    step's `info` (a study of where episodes fail reads Meta-World's stages from it)."""
    from sefa_sim.metaworld import make_env

    env = make_env(task, seed)
    try:
        executor.reset(seed)
        raw, _ = env.reset()
        success, t, limit = False, 0, min(max_steps, env.max_path_length)
        while t < limit and not success:
            action = executor.action(metaworld_observation(raw, keys))
            raw, _, _, truncated, info = env.step(np.clip(action, -1, 1))
            t += 1
            success = bool(info["success"])
            if watch is not None:
                watch(info)
            if truncated:
                break
        return {"task": task, "seed": seed, "success": success, "steps": t}
    finally:
        env.close()


def evaluate_metaworld(checkpoint: str | Path, tasks: list[str], env_name: str, *,
                       n_test: int = 50, start_seed: int = 100000, max_steps: int = 500,
                       solver: str | None = None, steps: int | None = None,
                       out: Path | None = None, device: str = "auto",
                       execution: ExecutionSettings | None = None, weak: Weak | None = None
                       ) -> dict | None:
    """Success rate over `n_test` seeds per task (each seed its own goal); for several tasks
    (a difficulty group) the mean over every episode, and each task's own rate. The log on
    rank 0 (None on the other ranks under torchrun)."""
    policy = Policy.load(checkpoint, device=device)
    per_seed, nfe = [], []
    executor = policy_executor(policy, execution, solver, steps, weak, nfe, device)
    started = time.perf_counter()
    # one list of (task, seed) pairs, so torchrun's ranks share every task's seeds
    pairs = [(task, seed) for task in tasks for seed in range(start_seed, start_seed + n_test)]
    mine = list(context().shard(pairs))
    started_rollouts(len(mine))
    for task, seed in mine:
        per_seed.append(metaworld_episode(executor, policy.cfg.shape_meta.obs, task, seed,
                                          max_steps))
        report("rollouts", len(per_seed), len(mine),
               success=f"{np.mean([r['success'] for r in per_seed]):.0%}")
    parts = context().gather(per_seed)
    if parts is None:
        return None
    per_seed = sorted((r for part in parts for r in part),
                      key=lambda r: (tasks.index(r["task"]), r["seed"]))
    rate = float(np.mean([r["success"] for r in per_seed]))
    per_task = {task: float(np.mean([r["success"] for r in per_seed if r["task"] == task]))
                for task in tasks}
    return _write_log({
        "env": env_name, "tasks": tasks, "checkpoint": policy.path, "kind": policy.kind,
        "solver": solver_label(policy.cfg, solver, steps), "nfe": mean_nfe(nfe),
        **execution_fields(executor),
        "test_start_seed": start_seed, "n_test": n_test, "max_steps": max_steps,
        # Meta-World reports the success rate; the mean score is the same number here
        "test/mean_score": rate, "test/success_rate": rate, "per_task_success_rate": per_task,
        "seconds": time.perf_counter() - started, "per_seed": per_seed}, out)
