"""Receding horizon against temporal ensembling, closed loop on Push-T (issue 24, point 2).

    python benchmarks/bench_execution.py [--policy CKPT_OR_EXPORT] [--seeds 20] [--json]

Every episode runs through the server's own `step` path (`PolicyService.handle` with a
connection's `Session`: the frame history, the execution state, the output checks), in process,
so what is measured is what `sefa serve --execution ...` does minus the socket. The modes are
paired: the same Push-T seeds (initial scenes) and the same policy; each episode's noise
generator is seeded with the episode's seed (the modes draw different numbers of noises, so
their noises differ after the first chunk).

Per mode it prints Push-T's score (Diffusion Policy's test score: the best min(coverage / 0.95,
1) reached), the success rate, the action smoothness, mean ||a_t - a_(t-1)||_2 over an
episode's steps (action units: Push-T's agent target in pixels), and the per-step server time
(`step_ms` of the replies) p50, p99 and jitter = p99 - p50; then the paired ratios ensemble /
receding (per seed, then the mean of those ratios).

Without --policy it makes a one-step student first the way benchmarks/bench_serve.py does
(`--train-steps`, the cpu profile's network size): a barely trained policy, so its scores say
how the modes compare on one policy, not what a trained one scores.
"""

from __future__ import annotations

import argparse
import asyncio
import importlib.util
import json
import tempfile
from pathlib import Path

import numpy as np

MODES = ("receding", "ensemble")


async def episode(service, env, seed: int, max_steps: int) -> dict:
    from sefa_sim.pusht import OBS_KEYS, SUCCESS_COVERAGE

    session = service.new_session()
    keys = [k for k in OBS_KEYS if k in service.meta["obs"]]

    async def run():
        await service.handle({"type": "reset", "seed": seed}, session)  # the episode's noise
        obs = env.reset(seed)
        best, coverage, actions, step_ms = 0.0, 0.0, [], []
        for _ in range(max_steps):
            frame = {k: np.asarray(obs[k], np.float32) for k in keys}
            reply = await service.handle({"type": "step", "obs": frame}, session)
            actions.append(np.asarray(reply["action"], np.float64))
            step_ms.append(reply["step_ms"])
            obs, reward, done, info = env.step(actions[-1])
            best, coverage = max(best, reward), max(coverage, float(info["coverage"]))
            if done:
                break
        a = np.stack(actions)
        jumps = np.linalg.norm(np.diff(a, axis=0), axis=1) if len(a) > 1 else np.zeros(1)
        return {"seed": seed, "score": best, "success": coverage > SUCCESS_COVERAGE, "steps": len(a),
                "smoothness": float(jumps.mean()), "step_ms": step_ms}
    return await run()


def run_mode(backend, mode: str, seeds: list[int], max_steps: int, replan_every, k) -> dict:
    from sefa_deploy.server import PolicyService
    from sefa_model.policy.execution import ExecutionSettings
    from sefa_sim.pusht import PushTEnv

    k = {"ensemble_k": k} if mode == "ensemble" else {}  # receding has no k
    service = PolicyService(backend, log=lambda s: None,
                            execution=ExecutionSettings(mode, replan_every, **k))
    env = PushTEnv()

    async def every_episode():  # one event loop: the service's worker answers on it
        return [await episode(service, env, s, max_steps) for s in seeds]
    per_seed = asyncio.run(every_episode())
    ms = np.concatenate([r.pop("step_ms") for r in per_seed])
    p50, p99 = np.percentile(ms, [50, 99])
    return {"replan_every": service.execution.replan_every, "mean_score": float(np.mean([r["score"] for r in per_seed])),
            "success_rate": float(np.mean([r["success"] for r in per_seed])),
            "mean_smoothness": float(np.mean([r["smoothness"] for r in per_seed])),
            "step_ms_p50": float(p50), "step_ms_p99": float(p99), "step_jitter_ms": float(p99 - p50),
            "steps": int(len(ms)), "per_seed": per_seed}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--policy", type=Path, help="checkpoint, run directory or `sefa export` directory")
    ap.add_argument("--store", type=Path, help="Push-T low-dim store (made when not given)")
    ap.add_argument("--train-steps", type=int, default=300)
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--start-seed", type=int, default=100000)  # Diffusion Policy's test seeds
    ap.add_argument("--max-steps", type=int, default=300)
    ap.add_argument("--ensemble-k", type=float, default=0.01)
    ap.add_argument("--ensemble-replan-every", type=int, default=None)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()

    from sefa_deploy.backends import load_backend

    with tempfile.TemporaryDirectory() as tmp:
        policy = args.policy
        if policy is None:
            spec = importlib.util.spec_from_file_location(
                "bench_serve", Path(__file__).with_name("bench_serve.py"))
            bench_serve = importlib.util.module_from_spec(spec)
            spec.loader.exec_module(bench_serve)
            policy, _, _ = bench_serve.make_checkpoints(Path(tmp), args.store, args.train_steps)
        backend = load_backend(policy, device="cpu")
        seeds = list(range(args.start_seed, args.start_seed + args.seeds))
        out = {"policy": str(args.policy or f"one-step student, {args.train_steps} steps"),
               "kind": backend.metadata["kind"], "n_action_steps": backend.metadata["n_action_steps"],
               "seeds": [seeds[0], seeds[-1]], "ensemble_k": args.ensemble_k}
        for name in MODES:
            every = args.ensemble_replan_every if name == "ensemble" else None
            out[name] = run_mode(backend, name, seeds, args.max_steps, every, args.ensemble_k)
    r, e = out["receding"]["per_seed"], out["ensemble"]["per_seed"]
    out["paired"] = {
        "score_diff_mean": float(np.mean([b["score"] - a["score"] for a, b in zip(r, e)])),
        "smoothness_ratio_mean": float(np.mean([b["smoothness"] / a["smoothness"]
                                                for a, b in zip(r, e) if a["smoothness"] > 0])),
        "ensemble_smoother_in": int(sum(b["smoothness"] < a["smoothness"] for a, b in zip(r, e))),
        "n": len(r)}
    if args.json:
        print(json.dumps(out, indent=2))
        return
    print(f"policy: {out['policy']} ({out['kind']}, n_action_steps {out['n_action_steps']}); "
          f"Push-T seeds {seeds[0]}..{seeds[-1]}, paired; ensemble k = {args.ensemble_k}")
    print(f"{'mode':10s} {'replan':>6s} {'score':>7s} {'success':>8s} {'|da| mean':>10s} "
          f"{'step p50':>9s} {'p99':>8s} {'jitter':>8s} {'steps':>6s}")
    for name in MODES:
        m = out[name]
        print(f"{name:10s} {m['replan_every']:6d} {m['mean_score']:7.3f} {m['success_rate']:8.0%} "
              f"{m['mean_smoothness']:10.3f} {m['step_ms_p50']:9.3f} {m['step_ms_p99']:8.3f} "
              f"{m['step_jitter_ms']:8.3f} {m['steps']:6d}")
    p = out["paired"]
    print(f"paired over {p['n']} seeds: score (ensemble - receding) {p['score_diff_mean']:+.3f}; "
          f"smoothness ratio ensemble / receding {p['smoothness_ratio_mean']:.3f} (mean of per-seed "
          f"ratios), ensemble smoother in {p['ensemble_smoother_in']} of {p['n']}")
    print("step times: server side (`step_ms`), ms; jitter = p99 - p50")


if __name__ == "__main__":
    main()
