"""How often a Push-T policy drives the agent out of the arena, and what clamping its actions to
the demonstrated range does (docs/results/pusht.md, "Execution: how each policy runs its chunks").

    python benchmarks/pusht_escapes.py W/distill --execution receding-8 receding-1 --n-test 500
    python benchmarks/pusht_escapes.py W/train --solver rk45 --execution receding-8 --n-test 200

Push-T's action is the agent's absolute target, followed by a PD controller with no limit: a
target far outside the 512 x 512 arena sends the agent through its walls, after which every
observation is unlike any in the demonstrations. For each execution, with and without the
clamp, the same episodes as `sefa eval --env pusht` (seeds from --start-seed, the noise seeded
per episode as there): the mean score, the episodes whose agent left the arena (its centre
outside [0, 512] in x or y, or not finite, at any step) and the others' mean score; and the
clamp's difference, paired over the seeds. The clamp bounds each action to the range of the
demonstrations' actions: [-1, 1] in the normalized space of a `limits` action normalizer
(Diffusion Policy's `clip_sample` does the same inside its diffusion sampler).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from reflow_rounds import paired  # mean of a - b over the same seeds, its standard error

ARENA = (0.0, 512.0)  # gym-pusht's walls stand at 5 and 506 px


def escaped(positions: np.ndarray, arena: tuple[float, float] = ARENA) -> bool:
    """Whether an episode's agent positions (T, 2) ever left the arena or stopped being finite."""
    p = np.asarray(positions, np.float64)
    return bool((~np.isfinite(p)).any() or (p < arena[0]).any() or (p > arena[1]).any())


def clamped(sample, low: np.ndarray, high: np.ndarray):
    """An executor's sampler whose chunks (N, T, Da) are clamped to [low, high] per dimension."""
    def clamped_sample(obs, noise, generator):
        return np.clip(np.asarray(sample(obs, noise, generator)), low, high)
    return clamped_sample


def action_bounds(policy) -> tuple[np.ndarray, np.ndarray]:
    """The demonstrated action range of a policy with a `limits` action normalizer: the actions
    that normalize to -1 and +1 (a constant dimension gets its value +-1, which it never
    leaves)."""
    import torch

    key = policy.cfg.shape_meta.action.key
    mode = policy.processor.normalizer_modes[key]
    if mode != "limits":
        raise SystemExit(f"{policy.path}: the action normalizer is '{mode}': the demonstrated "
                         "range is known for 'limits' only")
    d = policy.cfg.shape_meta.action.shape[-1]
    ends = policy.processor.action.unnormalize(torch.tensor([[-1.0] * d, [1.0] * d]))
    ends = ends.detach().cpu().numpy().astype(np.float64)
    return ends.min(axis=0), ends.max(axis=0)


def run(policy, spec: str, clamp: bool, seeds: range, solver: str | None,
        steps: int | None) -> list[dict]:
    from sefa_model.policy.execution import Executor, parse_spec, policy_sampler, policy_shape
    from sefa_sim.pusht import IMAGE_KEY, PushTEnv, episode, policy_names

    class TrackedEnv(PushTEnv):
        """PushTEnv recording the agent's position after every step."""
        def step(self, action):
            out = super().step(action)
            agent = self._env.agent.position
            self.track.append((agent.x, agent.y))
            return out

    sample = policy_sampler(policy, solver, steps)
    if clamp:
        sample = clamped(sample, *action_bounds(policy))
    executor = Executor(parse_spec(spec), sample, policy_shape(policy))
    feeds, _ = policy_names(list(policy.cfg.shape_meta.obs), None)
    env, out, started = TrackedEnv(), [], time.monotonic()
    for i, seed in enumerate(seeds, 1):
        env.track = []
        result = episode(executor, seed, env=env, feeds=feeds,
                         images=IMAGE_KEY in feeds.values())
        out.append({"seed": seed, "score": float(result["score"]),
                    "escaped": escaped(np.array(env.track).reshape(-1, 2))})
        if i % 25 == 0 and i < len(seeds):  # a plain line: these runs take up to an hour
            elapsed = time.monotonic() - started
            print(f"  {spec}{' clamped' if clamp else ''}: {i} of {len(seeds)} episodes, "
                  f"{elapsed:.0f} s, about {elapsed / i * (len(seeds) - i):.0f} s left",
                  flush=True)
    return out


def split_difference(a: list[dict], b: list[dict]) -> dict:
    """a's score minus b's over the seeds both ran, and its split into the seeds where a's agent
    left the arena and the others: each part's sum over all the shared seeds, so that the two
    parts add up to the mean difference."""
    theirs = {r["seed"]: r for r in b}
    shared = [r for r in a if r["seed"] in theirs]
    d = np.array([r["score"] - theirs[r["seed"]]["score"] for r in shared])
    out = np.array([r["escaped"] for r in shared], bool)
    n = len(shared)
    return {"n": n, "escaped": int(out.sum()),
            "other_escaped": int(sum(theirs[r["seed"]]["escaped"] for r in shared)),
            "minus": float(d.mean()), "from_escaped": float(d[out].sum() / n),
            "from_the_others": float(d[~out].sum() / n)}


def summary(rows: list[dict]) -> dict:
    kept = [r["score"] for r in rows if not r["escaped"]]
    return {"score": float(np.mean([r["score"] for r in rows])),
            "escaped": sum(r["escaped"] for r in rows), "n": len(rows),
            "score_not_escaped": float(np.mean(kept)) if kept else None}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("checkpoint", type=Path)
    ap.add_argument("--execution", nargs="+", default=["receding-8"],
                    help="MODE-K specs of one sample (receding-8, receding-1, ensemble-1)")
    ap.add_argument("--solver")
    ap.add_argument("--steps", type=int)
    ap.add_argument("--n-test", type=int, default=100)
    ap.add_argument("--start-seed", type=int, default=100_000)
    ap.add_argument("--json", type=Path, help="write every episode's score and escape here")
    ap.add_argument("--against", type=Path, help="another run's --json: this policy's score "
                    "minus that one's per execution, split by whether this one's agent left")
    args = ap.parse_args()
    if args.n_test < 1:
        raise SystemExit(f"pusht_escapes: --n-test must be 1 or more, not {args.n_test}")
    theirs = {}
    if args.against:  # read first: a bad file fails before an hour of rollouts, not after
        try:
            theirs = {r["execution"]: r["per_seed"]
                      for r in json.loads(args.against.read_text())["rows"] if not r["clamp"]}
        except (OSError, ValueError, KeyError, TypeError) as e:
            raise SystemExit(f"pusht_escapes: {args.against}: not a --json output of this script "
                             f"({type(e).__name__}: {e})") from None
    import torch

    from sefa_model.policy.artifact import Policy

    from sefa_data.errors import SefaInputError

    torch.set_num_threads(1)
    try:
        policy = Policy.load(args.checkpoint, device="cpu")
    except SefaInputError as e:
        raise SystemExit(f"pusht_escapes: {e}") from None
    seeds = range(args.start_seed, args.start_seed + args.n_test)
    out = {"checkpoint": str(args.checkpoint), "solver": args.solver, "steps": args.steps,
           "seeds": [seeds.start, seeds.stop], "rows": []}
    for spec in args.execution:
        per = {}
        for clamp in (False, True):
            started = time.monotonic()
            per[clamp] = run(policy, spec, clamp, seeds, args.solver, args.steps)
            s = summary(per[clamp])
            out["rows"].append({"execution": spec, "clamp": clamp, **s, "per_seed": per[clamp]})
            kept = "-" if s["score_not_escaped"] is None else f"{s['score_not_escaped']:.3f}"
            print(f"{spec:12s} {'clamped' if clamp else 'as sampled':10s} score {s['score']:.3f}, "
                  f"agent left the arena in {s['escaped']} of {s['n']} (the others {kept}); "
                  f"{time.monotonic() - started:.0f} s", flush=True)
        m, se = paired([r["score"] for r in per[True]], [r["score"] for r in per[False]])
        out["rows"][-1]["clamp_minus_sampled"] = [m, se]
        print(f"{spec:12s} clamped minus as sampled: {m:+.3f} ± {se or 0:.3f} over {len(seeds)} "
              "seeds", flush=True)
    if args.against:
        for row in (r for r in out["rows"] if not r["clamp"] and r["execution"] in theirs):
            row["against"] = s = split_difference(row["per_seed"], theirs[row["execution"]])
            print(f"{row['execution']:12s} minus {args.against.name}: {s['minus']:+.3f} over "
                  f"{s['n']} seeds (left the arena: {s['escaped']} here, {s['other_escaped']} "
                  f"there); {s['from_escaped']:+.3f} from the {s['escaped']} seeds whose agent left "
                  f"here, {s['from_the_others']:+.3f} from the others", flush=True)
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    sys.exit(main())
