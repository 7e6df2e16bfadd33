"""Push-T low-dim: the base flow's closed-loop score against its training steps (issue 11).

One run of the `cpu` profile's base flow (pipelines/pusht_lowdim_train.yaml) for --steps steps
keeps a checkpoint every --every steps (`training.keep_every`); each kept checkpoint is rolled
out with RK45 on the same test seeds. The checkpoints of one run share its cosine schedule, so
step k of a 50k run is not a k-step run (its learning rate has not decayed yet); the table says
where the score stops rising along this one schedule.

    python benchmarks/budget_curve.py -w runs/pusht --steps 50000 --every 5000 \\
        --evaluate 10000 30000 50000 --n-test 50 --final-n-test 200

The workspace needs the Push-T store (`sefa ingest ../shared/data/pusht_cchi_v7_replay.zarr
--fps 10 --key keypoint --key state --key action -w W`). Rollouts are cached per checkpoint and
seed count (W/base<steps>/curve/), so a rerun only evaluates what is missing; with --wait it
evaluates checkpoints as a running training writes them.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PRESET = "pipelines/pusht_lowdim_train.yaml"


def sefa(*args: str, capture: bool = False) -> str:
    print("$ sefa " + " ".join(args), flush=True)
    done = subprocess.run([sys.executable, "-m", "sefa_cli.main", *args], cwd=REPO, text=True,
                          stdout=subprocess.PIPE if capture else None)
    if done.returncode != 0:
        raise SystemExit(f"budget_curve: `sefa {' '.join(args)}` failed (exit {done.returncode})")
    return done.stdout or ""


def evaluate(ws: Path, ckpt: Path, n_test: int, out: Path) -> dict:
    log = out / "eval_log.json"
    if not log.exists():
        sefa("eval", str(ckpt), "--env", "pusht", "--n-test", str(n_test), "--solver", "rk45",
             "--out", str(out), "-w", str(ws), "--json", capture=True)
    data = json.loads(log.read_text())
    return {"score": data.get("test/mean_score"), "success": data.get("test/success_rate"),
            "n_test": n_test, "per_seed": data.get("per_seed")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("-w", "--workspace", type=Path, required=True)
    ap.add_argument("--steps", type=int, default=50000)
    ap.add_argument("--every", type=int, default=5000)
    ap.add_argument("--evaluate", type=int, nargs="*", help="steps to roll out (default: every kept one)")
    ap.add_argument("--n-test", type=int, default=50)
    ap.add_argument("--final-n-test", type=int, default=200, help="seeds for the last checkpoint")
    ap.add_argument("--wait", action="store_true", help="a training is running: wait for its checkpoints")
    args = ap.parse_args()
    ws = args.workspace.resolve()
    run = ws / f"base{args.steps // 1000}k"
    steps = args.evaluate or list(range(args.every, args.steps + 1, args.every))
    if not (run / "checkpoints" / "latest").exists() and not args.wait:
        # the run's own schedule, ending at --steps (the preset stops part-way along one)
        sefa("train", PRESET, f"training.max_steps={args.steps}", "training.lr_decay_steps=null",
             f"training.val_every={args.every}",
             f"training.checkpoint_every={args.every}", f"training.keep_every={args.every}",
             "--out", str(run), "-w", str(ws))
    rows = []
    for step in steps:
        ckpt = run / "checkpoints" / f"step_{step}"
        while args.wait and not (ckpt / "config.json").exists():
            time.sleep(30)
        n = args.final_n_test if step == args.steps else args.n_test
        result = evaluate(ws, ckpt, n, run / "curve" / f"step_{step}_rk45_{n}")
        val = [json.loads(line) for line in (run / "logs.jsonl").read_text().splitlines()
               if '"val_action_mse"' in line and json.loads(line)["step"] == step]
        rows.append({"step": step, **result, "val_action_mse": val[0]["val_action_mse"] if val else None})
        print(f"step {step}: score {result['score']:.3f}, success {result['success']:.0%} "
              f"({n} seeds)", flush=True)
    (run / "curve" / "curve.json").write_text(json.dumps(rows, indent=2))
    print("\n| training steps | RK45 score | success | seeds | val action MSE (px²) |")
    print("|---|---|---|---|---|")
    for r in rows:
        mse = "" if r["val_action_mse"] is None else f"{r['val_action_mse']:,.0f}"
        print(f"| {r['step']:,} | {r['score']:.3f} | {r['success']:.0%} | {r['n_test']} | {mse} |")


if __name__ == "__main__":
    main()
