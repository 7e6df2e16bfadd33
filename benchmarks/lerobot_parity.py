"""One policy scored by two evaluators: LeRobot's `lerobot-eval` (on a `sefa export --format
lerobot` folder) and `sefa eval --env pusht`, each with the standard error of its mean, and
their difference in standard errors of the difference.

    python benchmarks/lerobot_parity.py --sefa WS/evals/pusht-.../eval_log.json \\
        --lerobot OUT/eval_info.json [--json FILE]

Score: the episode's best reward min(coverage / 0.95, 1) (LeRobot's `avg_max_reward`, sefa's
`test/mean_score`); success: coverage over 0.95 (`pc_success`, `test/success_rate`). The two
draw their scenes differently (sefa: Diffusion Policy's seeds 100000+; LeRobot: gym-pusht's own
reset from --seed), so the episodes are not paired: each mean has its own standard error,
std / sqrt(n), and the difference's is the root of their squares.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path


def mean_se(values: list[float]) -> tuple[float, float]:
    n = len(values)
    mean = sum(values) / n
    var = sum((v - mean) ** 2 for v in values) / (n - 1) if n > 1 else 0.0
    return mean, math.sqrt(var / n)


def sefa_episodes(path: Path) -> dict[str, list[float]]:
    seeds = json.loads(path.read_text())["per_seed"]
    return {"score": [s["score"] for s in seeds], "success": [float(s["success"]) for s in seeds]}


def lerobot_episodes(path: Path) -> dict[str, list[float]]:
    info = json.loads(path.read_text())
    score, success = [], []
    for task in info["per_task"]:
        score += task["metrics"]["max_rewards"]
        success += [float(s) for s in task["metrics"]["successes"]]
    return {"score": score, "success": success}


def compare(sefa: dict[str, list[float]], lerobot: dict[str, list[float]]) -> dict:
    out = {"n": {"sefa": len(sefa["score"]), "lerobot": len(lerobot["score"])}}
    for metric in ("score", "success"):
        (a, sa), (b, sb) = mean_se(sefa[metric]), mean_se(lerobot[metric])
        se = math.hypot(sa, sb)
        out[metric] = {"sefa": a, "sefa_se": sa, "lerobot": b, "lerobot_se": sb,
                       "difference": b - a, "difference_se": se,
                       "z": (b - a) / se if se > 0 else 0.0}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sefa", type=Path, required=True, help="sefa eval's eval_log.json")
    ap.add_argument("--lerobot", type=Path, required=True, help="lerobot-eval's eval_info.json")
    ap.add_argument("--json", type=Path, help="also write the comparison here")
    args = ap.parse_args()
    result = compare(sefa_episodes(args.sefa), lerobot_episodes(args.lerobot))
    print(f"episodes: sefa eval {result['n']['sefa']}, lerobot-eval {result['n']['lerobot']}")
    for metric in ("score", "success"):
        r = result[metric]
        print(f"{metric:8s} sefa eval {r['sefa']:.3f} ± {r['sefa_se']:.3f}   lerobot-eval "
              f"{r['lerobot']:.3f} ± {r['lerobot_se']:.3f}   difference {r['difference']:+.3f} "
              f"± {r['difference_se']:.3f} ({r['z']:+.2f} s.e.)")
    if args.json:
        args.json.write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
