"""Push-T from the camera (issue 14): the base image flow, its one-step Euler sampling and the
SeFA one-step student, each in closed loop on the same test seeds, with latency split into the
image encoder and the action head.

    python benchmarks/pusht_image.py --profile cpu  [--n-test 100] [--workspace runs/image-cpu]
    python benchmarks/pusht_image.py --profile full                 # a GPU: ResNet-18, U-Net

It runs `sefa` commands in one workspace, each printed before it runs:

    sefa ingest DATA/pusht_cchi_v7_replay.zarr --fps 10 --key img --key state --key action
    sefa run <pipeline preset>                       # train, reflow, align, distill
    sefa eval train --env pusht --solver rk45 | --solver euler --steps 1
    sefa eval distill --env pusht
    sefa bench latency train@rk45 train@euler-1 distill

--data DATA is the folder holding Diffusion Policy's Push-T zarr (its pusht.zip unpacks to
pusht/). The SeFA stages use the base encoder's frozen features, computed once (WORKSPACE/features).
Rows and their commands go to docs/data/pusht_image_<profile>.json; an interrupted run
continues (stages and evaluations are cached by the workspace).
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from sefa_data.bench.throughput import DEFAULT_DATA_DIR

from sefa_data import atomic

REPO = Path(__file__).resolve().parents[1]
PUSHT_FILE = "pusht_cchi_v7_replay.zarr"
PROFILES = {"cpu": "pipelines/pusht_image.yaml", "full": "pipelines/pusht_image_full.yaml"}
ROWS = [  # (name, checkpoint, solver args, latency target suffix)
    ("base flow, RK45", "train", ["--solver", "rk45"], "@rk45"),
    ("base flow, Euler-1", "train", ["--solver", "euler", "--steps", "1"], "@euler-1"),
    ("SeFA one-step, eps 0.05", "distill", [], ""),
]


def sefa(workspace: Path, args: list[str], commands: list[str], capture: bool = False) -> str:
    line = "sefa " + " ".join(args)
    commands.append(line)
    print(f"$ {line}", flush=True)
    done = subprocess.run([sys.executable, "-m", "sefa_cli.main", *args, "-w", str(workspace)], cwd=REPO,
                          text=True, stdout=subprocess.PIPE if capture else None)
    if done.returncode != 0:
        raise SystemExit(f"pusht_image: `{line}` failed (exit {done.returncode})")
    return done.stdout or ""


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--profile", choices=sorted(PROFILES), default="cpu")
    ap.add_argument("--workspace", type=Path, default=None, help="default: runs/image-<profile>")
    ap.add_argument("--n-test", type=int, default=100)
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA_DIR,
                    help="the folder holding pusht_cchi_v7_replay.zarr (Diffusion Policy's pusht.zip unpacks to pusht/)")
    ap.add_argument("--out", type=Path, default=None, help="default: docs/data/pusht_image_<profile>.json")
    args = ap.parse_args(argv)
    ws = (args.workspace or REPO / "runs" / f"image-{args.profile}").resolve()
    pipeline = PROFILES[args.profile]
    out = args.out or REPO / "docs" / "data" / f"pusht_image_{args.profile}.json"
    commands: list[str] = []
    started = time.perf_counter()
    if not (ws / "dataset.zarr").exists():
        sefa(ws, ["ingest", str(args.data / PUSHT_FILE), "--fps", "10", "--key", "img", "--key", "state", "--key", "action"],
             commands)
    sefa(ws, ["run", str(REPO / pipeline)], commands)
    rows = []
    for name, ckpt, solver, _ in ROWS:
        log = json.loads(sefa(ws, ["eval", str(ws / ckpt), "--env", "pusht", "--n-test", str(args.n_test),
                                   *solver, "--json"], commands, capture=True))[0]
        per_seed = json.loads((ws / log["eval_log"]).read_text())["per_seed"]
        scores = np.array([r["score"] for r in per_seed])
        rows.append({"name": name, "checkpoint": ckpt, "solver": log["solver"],
                     "score": float(scores.mean()),
                     "score_se": float(scores.std(ddof=1) / np.sqrt(len(scores))),
                     "success_rate": log["test/success_rate"], "n_test": log["n_test"],
                     "per_seed_scores": scores.round(4).tolist(), "command": commands[-1]})
    targets = [str(ws / ckpt) + suffix for _, ckpt, _, suffix in ROWS]
    latency = json.loads(sefa(ws, ["bench", "latency", *targets, "--device", "auto", "--passes", "3",
                                   "--max-seconds", "10", "--json"], commands, capture=True))
    for row, timing in zip(rows, latency["rows"]):
        row.update({k: timing[k] for k in ("nfe", "p50_ms", "encoder_ms", "head_ms", "forward_ms")})
    manifests = {a: json.loads((ws / a / "manifest.json").read_text()).get("summary", {})
                 for a in ("train", "reflow/iter_1", "align", "distill") if (ws / a / "manifest.json").exists()}
    result = {"profile": args.profile, "pipeline": pipeline, "workspace": str(ws),
              "machine": latency.get("machine"), "device": latency.get("device"),
              "rows": rows, "stages": manifests, "commands": commands,
              "seconds": time.perf_counter() - started}
    atomic.write_json(out, result)
    print(f"\n{'policy':28s} {'score':>13s} {'success':>8s} {'NFE':>4s} {'p50 ms':>8s} "
          f"{'encoder':>8s} {'head':>8s}")
    for r in rows:
        print(f"{r['name']:28s} {r['score']:.3f} ± {r['score_se']:.3f} {r['success_rate']:8.0%} "
              f"{r['nfe']:4d} {r['p50_ms']:8.2f} {r['encoder_ms']:8.2f} {r['head_ms']:8.3f}")
    print(f"written: {out}")
    return result


if __name__ == "__main__":
    main()
