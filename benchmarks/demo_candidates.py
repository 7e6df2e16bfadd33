"""Which task `sefa demo` runs: each candidate through the demo itself, timed.

    OMP_NUM_THREADS=1 python benchmarks/demo_candidates.py --root R --tasks button-press reach
    python benchmarks/demo_candidates.py --root R --report-only

Each task runs `run_demo` (pipelines/builtin_demo.py: scripted demonstrations, ingest, the
pipeline of pipelines/builtin_default.yaml or the sizes given here, the demo's table) in its
own workspace R/<task>, in one process on one torch thread, one task after another. Each task's
row goes into R/candidates.json when it is done: every table row (success rate, NFE, latency),
the seconds of each stage and evaluation, and the CPU seconds of the whole run (user + system:
on a busy machine the wall time measures the other jobs; the CPU time is what one quiet core
would take). A task already in the file is skipped, so an interrupted study continues.
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def cpu_seconds() -> float:
    me = resource.getrusage(resource.RUSAGE_SELF)
    return me.ru_utime + me.ru_stime


def stage_seconds(workspace: Path) -> dict[str, float]:
    """Each stage's recorded duration (its manifest) and each evaluation's (its log)."""
    from sefa_pipelines.runner import Workspace

    ws = Workspace(workspace)
    out = {}
    for stage in ("train", "reflow/iter_1", "align", "distill"):
        try:
            out[stage] = ws.read_manifest(stage)["duration_s"]
        except Exception:  # noqa: BLE001 (a stage this pipeline has not got)
            continue
    for log in sorted((workspace / "evals").glob("*/eval_log.json")):
        rec = json.loads(log.read_text())
        run = Path(rec["checkpoint"]).parts[-3]  # train or distill
        name = f"eval {rec['solver']} {rec['execution_label']} ({run})"
        out[name] = round(rec["seconds"], 1)
    return out


def pipeline(args):
    """builtin_default.yaml with the sizes given on the command line."""
    from sefa_pipelines.builtin_demo import demo_pipeline

    cfg = demo_pipeline()
    if args.max_windows is not None:
        cfg.reflow.max_windows = args.max_windows
    if args.student_steps is not None:
        cfg.distill.train_overrides = [o for o in cfg.distill.train_overrides
                                       if not o.startswith("training.max_steps=")]
        cfg.distill.train_overrides.append(f"training.max_steps={args.student_steps}")
    if args.base_steps is not None:
        cfg.train = [f"training.max_steps={args.base_steps}"]
    return cfg


def run_task(root: Path, task: str, args) -> dict:
    import torch

    from sefa_pipelines.builtin_demo import run_demo

    torch.set_num_threads(1)
    workspace = root / task
    started, cpu0 = time.monotonic(), cpu_seconds()
    summary = run_demo(workspace, log=lambda line: print(line, file=sys.stderr, flush=True),
                       task=task, episodes=args.episodes, n_test=args.n_test,
                       pipeline=pipeline(args))
    return {"wall_s": round(time.monotonic() - started, 1),
            "cpu_s": round(cpu_seconds() - cpu0, 1),
            "stages_s": stage_seconds(workspace),
            "rows": summary["policy"]["rows"],
            "settings": {"episodes": args.episodes, "n_test": args.n_test,
                         "base_steps": args.base_steps, "student_steps": args.student_steps,
                         "max_windows": args.max_windows}}


def report(results: dict) -> str:
    lines = ["| task | policy | execution | success | NFE | ms per prediction |",
             "|---|---|---|---|---|---|"]
    for task, r in results.items():
        for row in r["rows"]:
            lines.append(f"| {task} | {row['policy']} | {row['execution']} | "
                         f"{row['success_rate']:.0%} of {row['n_test']} | {row['nfe']} | "
                         f"{row['latency_ms']:.2f} |")
    lines.append("")
    for task, r in results.items():
        lines.append(f"{task}: {r['cpu_s']:.0f} CPU s ({r['wall_s']:.0f} s wall); "
                     + ", ".join(f"{k} {v:.0f} s" for k, v in r["stages_s"].items()))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root", type=Path, default=REPO / "runs" / "demo-candidates")
    parser.add_argument("--tasks", nargs="*", default=[])
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--n-test", type=int, default=50)
    parser.add_argument("--base-steps", type=int, default=None)
    parser.add_argument("--student-steps", type=int, default=None)
    parser.add_argument("--max-windows", type=int, default=None)
    parser.add_argument("--report-only", action="store_true")
    args = parser.parse_args(argv)
    args.root.mkdir(parents=True, exist_ok=True)
    path = args.root / "candidates.json"
    results = json.loads(path.read_text()) if path.exists() else {}
    for task in [] if args.report_only else args.tasks:
        if task in results:
            continue
        results[task] = run_task(args.root, task, args)
        path.write_text(json.dumps(results, indent=1))
    print(report(results))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
