"""Closed-loop evaluations of one workspace, each paired with a reference over the seeds both ran.

    python benchmarks/paired_evals.py -w W --against reflow1_noalign [--json OUT]

Reads every `sefa eval --env` log in W/evals (eval_log.json, per-seed scores; Push-T's score,
a success rate's 0 or 1) and prints, per evaluation, its score, success rate and seed count,
and its score minus the reference's as the mean of the per-seed differences ± their standard
error (`reflow_rounds.paired`: the seeds' difficulty cancels; the longer one cut to the
shorter's seeds; evaluations on other seeds, such as `sefa choose-execution`'s validation
seeds, are listed unpaired). An evaluation is named by the policy's folder under W/rows/ when it is a
snapshot there, else by its run's folder (or the checkpoint path), then the solver and the
execution in brackets (`distill [euler-1, receding K=8]`), then its seeds when the same
policy ran on others too. --json writes the per-seed scores (docs/data).
"""

from __future__ import annotations

import argparse
import json
from collections import Counter
from pathlib import Path

from reflow_rounds import paired


def evaluations(ws: Path) -> dict[str, dict]:
    named = []
    for log in sorted(ws.glob("evals/*/eval_log.json")):
        d = json.loads(log.read_text())
        ckpt = d["checkpoint"]
        name = ckpt.split("rows/")[1].split("/")[0] if "rows/" in ckpt else ckpt
        if "rows/" not in ckpt and "/checkpoints/" in ckpt:  # a run of the workspace: its folder
            name = Path(ckpt.split("/checkpoints/")[0]).name
        how = ", ".join(x for x in (d.get("solver"), d.get("execution_label")) if x)
        named.append((f"{name} [{how}]", d))
    counts = Counter(name for name, _ in named)
    # the same policy on other seeds: each named by its seeds
    return dict(sorted((name if counts[name] == 1 else
                        f"{name} {d['n_test']} seeds from {d['test_start_seed']}", d)
                       for name, d in named))


def scores(d: dict) -> list[float]:
    return [float(p.get("score", p["success"]))
            for p in sorted(d["per_seed"], key=lambda p: (p.get("task", ""), p["seed"]))]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-w", "--workspace", type=Path, required=True)
    ap.add_argument("--against", required=True, help="a policy's name, or a part of it")
    ap.add_argument("--json", type=Path, help="write the per-seed scores here")
    args = ap.parse_args()
    evals = evaluations(args.workspace)
    ref = [k for k in evals if args.against in k]
    if len(ref) != 1:
        raise SystemExit(f"--against {args.against}: matches {ref or 'no evaluation'} "
                         f"(evaluated: {', '.join(evals)})")
    base = evals[ref[0]]
    for name, d in evals.items():
        line = (f"{name:60s} score {d['test/mean_score']:.3f}  success {d['test/success_rate']:.1%}"
                f"  seeds {d['n_test']}")
        if d["test_start_seed"] != base["test_start_seed"]:  # `sefa choose-execution`'s
            line += f"  (seeds from {d['test_start_seed']}: not paired)"  # validation seeds
        elif name != ref[0]:
            diff, se = paired(scores(d), scores(base))
            line += f"  minus the reference: {diff:+.3f} ± {se or 0:.3f}"
        print(line)
    if args.json:
        args.json.write_text(json.dumps({name: {
            "checkpoint": d["checkpoint"], "kind": d["kind"], "solver": d["solver"],
            "start_seed": d["test_start_seed"],
            "mean_score": d["test/mean_score"], "success_rate": d["test/success_rate"],
            "execution": d.get("execution_label"), "per_seed": [
                {"seed": p["seed"], **({"task": p["task"]} if "task" in p else {}),
                 "score": float(p.get("score", p["success"])), "success": p["success"]}
                for p in d["per_seed"]]} for name, d in evals.items()}, indent=1))


if __name__ == "__main__":
    main()
