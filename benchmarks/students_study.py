"""The one-step students on Push-T low-dim, each paired against its RK45 teacher: which recipe
keeps the multi-step policy's accuracy at one network evaluation, and does alignment help it?

    python benchmarks/students_study.py -w W [--rows ...] [--student-steps 2000] [--json OUT]

W is a workspace of the `cpu` profile (`sefa ingest ../shared/data/pusht_cchi_v7_replay.zarr
--fps 10 --key keypoint --key state --key action -w W`, `pipelines/pusht_lowdim.yaml` as its
sefa.yaml): its base flow (`sefa train`), couplings (`sefa reflow`: 3,000 windows x K = 10)
and alignment (`sefa align`, eps 0.05) are the stages' own and cached. Each row's student is
trained from the same base flow with `sefa distill --method M [--no-align]`'s settings
(sefa_pipelines.stages.student_config; --student-steps steps), into W/<rows dir>/<row> (--rows-dir,
rows37 by default: a second setting of the same rows goes into its own folder), and rolled out
on the Push-T test seeds from 100000 (one-step rows --n-test, 500 by default; the teacher
--teacher-n-test, 200). Every finished training and rollout is kept, so an interrupted study
continues where it stopped. Rows:

    teacher_rk45        the base flow, RK45 (rtol = atol = 1e-5)
    base_euler1         the base flow, one Euler step
    reference_aligned   the reference student (MSE at t = 0) on the aligned couplings (SeFA)
    reference_plain     the same on the unaligned couplings (plain reflow)
    rfpp_aligned        2-rectified-flow++ on the aligned couplings
    rfpp_plain          the same on the unaligned couplings
    mean_flow           a mean-flow student: the base flow distilled on fresh noise
    shortcut            a shortcut student: the base flow distilled on fresh noise

Printed: per row score, success, seeds, training time, and the score minus the teacher's and
minus the reference student's (aligned), each the mean of per-seed differences ± its standard
error over the seeds both ran.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

ROWS = {  # name: (method, couplings: "aligned" | "plain" | None, solver, steps)
    "teacher_rk45": (None, None, "rk45", None),
    "base_euler1": (None, None, "euler", 1),
    "reference_aligned": ("reference", "aligned", None, None),
    "reference_plain": ("reference", "plain", None, None),
    "rfpp_aligned": ("rfpp", "aligned", None, None),
    "rfpp_plain": ("rfpp", "plain", None, None),
    "mean_flow": ("mean_flow", None, None, None),
    "shortcut": ("shortcut", None, None, None),
}


def paired(a: list[float], b: list[float]) -> tuple[float, float | None]:
    """Mean of a - b over the seeds both ran (both start at the same seed) and its standard error."""
    n = min(len(a), len(b))
    diff = np.asarray(a[:n]) - np.asarray(b[:n])
    return float(diff.mean()), (float(diff.std(ddof=1) / np.sqrt(n)) if n > 1 else None)


def scores(log: dict) -> list[float]:
    return [p["score"] for p in sorted(log["per_seed"], key=lambda p: p["seed"])]


def train_row(ws: Path, name: str, steps: int, log) -> tuple[Path, float | None]:
    """The row's student checkpoint, trained unless it is there; (checkpoint, seconds or None)."""
    from sefa_pipelines.stages import (COUPLINGS, FEATURES_DIR, base_train_config, load_pipeline,
                                  student_config)
    from sefa_model.data.couplings import PairSource
    from sefa_model.train.loop import train

    method, couplings, _, _ = ROWS[name]
    out = ws / ROWS_DIR[0] / name
    ckpt = out / "checkpoints" / "latest"
    if (out / "done.json").exists():
        return ckpt, json.loads((out / "done.json").read_text())["seconds"]
    cfg = student_config(base_train_config(ws, load_pipeline(ws)),
                         [f"training.max_steps={steps}", f"training.val_every={steps}",
                          f"training.checkpoint_every={max(1, steps // 4)}"], method=method)
    source = None
    if couplings == "aligned":
        source = PairSource.aligned(ws / "align" / "aligned.zarr", "sefa_one_step")
    elif couplings == "plain":
        source = PairSource.couplings(ws / "reflow" / "iter_1" / COUPLINGS, "reflow_one_step")
    log(f"{name}: training {method} for {steps} steps")
    started = time.perf_counter()
    resume = (ckpt / "config.json").exists()
    train(cfg, out, ws / "dataset.zarr", init_from=ws / "train" / "checkpoints" / "latest",
          couplings=source, features_cache=ws / FEATURES_DIR, resume=resume)
    seconds = time.perf_counter() - started
    (out / "done.json").write_text(json.dumps({"seconds": seconds, "steps": steps, "resumed": resume}))
    return ckpt, seconds


ROWS_DIR = ["rows37"]  # the folder of the rows, set once by --rows-dir
BLOCK = 50  # seeds per kept rollout block: a study stopped part-way keeps its finished blocks


def kept_blocks(ws: Path, name: str, n_test: int) -> int:
    """How many of a row's first seeds have kept rollouts (consecutive blocks from the first)."""
    from sefa_sim.pusht import FIRST_TEST_SEED

    done = 0
    for first in range(FIRST_TEST_SEED, FIRST_TEST_SEED + n_test, BLOCK):
        n = min(BLOCK, FIRST_TEST_SEED + n_test - first)
        if not (ws / ROWS_DIR[0] / name / f"eval_{first}_{n}" / "eval_log.json").exists():
            break
        done += n
    return done


def evaluate_row(ws: Path, name: str, ckpt: Path, n_test: int, log, upto: int | None = None) -> dict:
    """Rollouts on seeds 100000 .. 100000 + n_test - 1, in blocks of BLOCK seeds, each kept in
    W/<rows dir>/<row>/eval_<first seed>/ and reused; the blocks' per-seed scores joined. `upto`:
    only the blocks before this seed (the study runs block by block over its rows)."""
    from sefa_sim.pusht import FIRST_TEST_SEED
    from sefa_sim.rollouts import evaluate_pusht

    _, _, solver, steps = ROWS[name]
    per_seed = []
    last = FIRST_TEST_SEED + n_test if upto is None else min(upto, FIRST_TEST_SEED + n_test)
    for first in range(FIRST_TEST_SEED, last, BLOCK):
        n = min(BLOCK, FIRST_TEST_SEED + n_test - first)
        out = ws / ROWS_DIR[0] / name / f"eval_{first}_{n}"
        if (out / "eval_log.json").exists():
            block = json.loads((out / "eval_log.json").read_text())
        else:
            log(f"{name}: Push-T rollouts on seeds {first}..{first + n - 1}")
            block = evaluate_pusht(ckpt, n_test=n, start_seed=first, solver=solver, steps=steps,
                                   out=out, device="cpu")
        per_seed += block["per_seed"]
    scores_ = [p["score"] for p in per_seed]
    return {"per_seed": per_seed, "n_test": len(per_seed), "test/mean_score": float(np.mean(scores_)),
            "test/success_rate": float(np.mean([p.get("success", p["score"] >= 1.0) for p in per_seed]))}


TAIL_BINS = (-1.0, -0.5, -0.2, -0.05, 0.05, 0.2, 0.5, 1.0001)


def tails(a: list[float], b: list[float]) -> list[tuple[int, float]]:
    """Per-seed differences a - b over the seeds both ran, binned by TAIL_BINS: (seeds, their
    summed difference) per bin. The sums add up to n times the paired mean."""
    n = min(len(a), len(b))
    d = np.asarray(a[:n]) - np.asarray(b[:n])
    return [(int(((d >= lo) & (d < hi)).sum()), float(d[(d >= lo) & (d < hi)].sum()))
            for lo, hi in zip(TAIL_BINS[:-1], TAIL_BINS[1:])]


def print_tails(results: dict) -> None:
    bins = [f"[{lo:+.2f}, {hi:+.2f})" for lo, hi in zip(TAIL_BINS[:-1], TAIL_BINS[1:])]
    print("\nPer-seed score minus the teacher's: seeds (summed difference) in each range")
    print("| row | " + " | ".join(bins) + " |")
    print("|---|" + "---|" * len(bins))
    for name, r in results.items():
        if name != "teacher_rk45":
            cells = [f"{k} ({s:+.2f})" for k, s in tails(r["scores"], results["teacher_rk45"]["scores"])]
            print(f"| {name} | " + " | ".join(cells) + " |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-w", "--workspace", type=Path, required=True)
    ap.add_argument("--rows", nargs="+", default=list(ROWS), choices=list(ROWS))
    ap.add_argument("--student-steps", type=int, default=2000)
    ap.add_argument("--n-test", type=int, default=500)
    ap.add_argument("--teacher-n-test", type=int, default=200)
    ap.add_argument("--first-seeds", type=int, help="this run: only the first N seeds of each row "
                    "(a later run with more continues from the kept blocks)")
    ap.add_argument("--report", action="store_true", help="run nothing: the table from the "
                    "trainings and rollout blocks kept so far (each row's consecutive blocks)")
    ap.add_argument("--rows-dir", default="rows37", help="the rows' folder in the workspace (link "
                    "teacher_rk45 and base_euler1 there from another to reuse their rollouts)")
    ap.add_argument("--tails", action="store_true", help="also: where each row's paired difference "
                    "with the teacher comes from (seeds by how much they lose or gain)")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    ROWS_DIR[0] = args.rows_dir
    ws = args.workspace.resolve()
    log = lambda line: print(line, flush=True)  # noqa: E731
    from sefa_sim.pusht import FIRST_TEST_SEED

    if args.report:
        args.rows = [r for r in args.rows if ROWS[r][0] is None
                     or (ws / ROWS_DIR[0] / r / "done.json").exists()]
        counts = {r: kept_blocks(ws, r, args.teacher_n_test if r == "teacher_rk45" else args.n_test)
                  for r in args.rows}
        args.rows = [r for r in args.rows if counts[r]]
        args.first_seeds = None
    trained = {}
    for name in args.rows:  # every student first: then each block of seeds covers every row
        if ROWS[name][0] is None:
            trained[name] = (ws / "train" / "checkpoints" / "latest", None)
        else:
            trained[name] = train_row(ws, name, args.student_steps, log)
    n_of = {name: args.teacher_n_test if name == "teacher_rk45" else args.n_test for name in args.rows}
    if args.first_seeds:
        n_of = {name: min(n, args.first_seeds) for name, n in n_of.items()}
    if args.report:
        n_of = counts
    for upto in range(FIRST_TEST_SEED + BLOCK, FIRST_TEST_SEED + max(n_of.values()) + BLOCK, BLOCK):
        for name in args.rows:  # block by block over the rows: a stopped study stays paired
            evaluate_row(ws, name, trained[name][0], n_of[name], log, upto=upto)
    results = {}
    for name in args.rows:
        method = ROWS[name][0]
        ckpt, seconds = trained[name]
        ev = evaluate_row(ws, name, ckpt, n_of[name], log)
        results[name] = {"method": method, "couplings": ROWS[name][1], "train_seconds": seconds,
                         "score": ev["test/mean_score"], "success": ev["test/success_rate"],
                         "n_test": ev["n_test"], "scores": scores(ev)}
        log(f"{name}: score {ev['test/mean_score']:.3f} on {ev['n_test']} seeds")
    print("\n| row | method | couplings | score | success | seeds | train s | - teacher RK45 | - reference (aligned) |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name, r in results.items():
        cells = []
        for ref in ("teacher_rk45", "reference_aligned"):
            if ref in results and ref != name:
                d, se = paired(r["scores"], results[ref]["scores"])
                cells.append(f"{d:+.3f} ± {se:.3f}" if se is not None else f"{d:+.3f}")
            else:
                cells.append("-")
        secs = "-" if r["train_seconds"] is None else f"{r['train_seconds']:.0f}"
        print(f"| {name} | {r['method'] or 'base flow'} | {r['couplings'] or '-'} | {r['score']:.3f} "
              f"| {r['success']:.1%} | {r['n_test']} | {secs} | {cells[0]} | {cells[1]} |")
    if args.tails and "teacher_rk45" in results:
        print_tails(results)
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
