"""The time-embedding study (issue 26): how `flow.time_scale` (the network sees t * time_scale
through a sinusoidal embedding) shapes the base flow's cost and accuracy.

    bash benchmarks/time_scale_bases.sh W cuda            # the rows' base flows (a GPU: minutes)
    python benchmarks/time_scale_study.py -w W [--reflow] [--against 999] [--json OUT]

Per row W/rows/ts<SCALE> (each a base flow of the `cpu` profile differing only in the scale):
RK45 network evaluations per chunk at rtol = atol = 1e-5 and the validation action MSE on 256
windows (`sefa eval ROW --offline`), the closed-loop score on the first 200 Push-T test seeds
with RK45 and with Euler-1/2/4 (`sefa eval ROW --env pusht [--solver euler --steps K]`), each
paired over the seeds against the --against row, and with --reflow the coupling throughput and
accuracy of benchmarks/bench_reflow.py on that row (its reference's loop, the batched solve at
the reference's tolerance, and the fastest solver at equal accuracy). Evaluations are cached by
`sefa eval`, bench_reflow results in W/bench_reflow_ts<SCALE>.json, so a rerun only adds what
is missing. --jobs runs that many evaluations side by side (one CPU thread each).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from reflow_rounds import paired

REPO = Path(__file__).resolve().parents[1]
SOLVERS = (("rk45", []), ("euler-1", ["--solver", "euler", "--steps", "1"]),
           ("euler-2", ["--solver", "euler", "--steps", "2"]), ("euler-4", ["--solver", "euler", "--steps", "4"]))


def sefa_json(ws: Path, *args: str) -> dict:
    done = subprocess.run([sys.executable, "-m", "sefa_cli.main", *args, "--json", "-w", str(ws)],
                          cwd=REPO, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"`sefa {' '.join(args)}` failed: {done.stderr.strip().splitlines()[-1:]}")
    return json.loads(done.stdout)[0]


def per_seed(ws: Path, result: dict) -> list[float]:
    log = json.loads((ws / result["eval_log"]).read_text())
    return [p["score"] for p in sorted(log["per_seed"], key=lambda p: p["seed"])]


def measure_row(ws: Path, scale: str, n_test: int, jobs: int) -> dict:
    row_dir = str(ws / "rows" / f"ts{scale}")
    calls = {"offline": ["eval", row_dir, "--offline", "--windows", "256", "--threads", "1"]}
    for name, args in SOLVERS:
        calls[name] = ["eval", row_dir, "--env", "pusht", "--n-test", str(n_test), *args, "--threads", "1"]
    with ThreadPoolExecutor(jobs) as pool:
        results = dict(zip(calls, pool.map(lambda a: sefa_json(ws, *a), calls.values())))
    off = results.pop("offline")
    row = {"time_scale": float(scale), "rk45_nfe_per_chunk": off["nfe"],
           "val_action_mse": off["action_mse"], "spread_ratio": off["spread_ratio"]}
    for name, r in results.items():
        row[name] = {"score": r["test/mean_score"], "success_rate": r["test/success_rate"],
                     "n_test": r["n_test"], "nfe": r["nfe"], "per_seed": per_seed(ws, r),
                     "command": f"sefa eval rows/ts{scale} --env pusht --n-test {n_test} "
                                + " ".join(dict(SOLVERS)[name])}
    return row


def reflow_bench(ws: Path, scale: str) -> dict:
    out = ws / f"bench_reflow_ts{scale}.json"
    if not out.exists():
        cmd = [sys.executable, str(REPO / "benchmarks" / "bench_reflow.py"), "--checkpoint",
               str(ws / "rows" / f"ts{scale}"), "--store", str(ws / "dataset.zarr"), "--save", str(out)]
        print("$ " + " ".join(cmd), flush=True)
        if subprocess.run(cmd, cwd=REPO, stdout=subprocess.DEVNULL).returncode != 0:
            raise SystemExit(f"bench_reflow failed on time_scale {scale}")
    b = json.loads(out.read_text())
    rows = {r["key"]: r for r in b["rows"]}
    best = max((r for r in b["rows"] if r["key"] != "reference" and r["equal_accuracy"]
                and r["device"] == "cpu"), key=lambda r: r["speedup"], default=None)
    pick = lambda r: None if r is None else {
        k: r.get(k) for k in ("method", "couplings_per_s", "evals_per_coupling", "mean_err", "max_err", "speedup")}
    return {"reference": pick(rows["reference"]), "batched_at_reference_tolerance": pick(rows.get("rk45@ref")),
            "best_at_equal_accuracy": pick(best), "file": out.name}


def table(rows: list[dict], against: str) -> str:
    ref = next(r for r in rows if f"{r['time_scale']:g}" == against)
    lines = ["| time_scale | RK45 NFE / chunk | val action MSE (px²) | RK45 score (200) | "
             f"- {against} (paired) | Euler-1 | Euler-2 | Euler-4 | couplings/s: reference, batched at its tol, "
             "best at equal accuracy (x reference) |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        cells = []
        for name in ("rk45", "euler-1", "euler-2", "euler-4"):
            d, se = paired(r[name]["per_seed"], ref[name]["per_seed"])
            cells.append(f"{r[name]['score']:.3f}" + ("" if r is ref else f" ({d:+.3f} ± {se:.3f})"))
        rk45, rest = cells[0].split(" (")[0], cells[1:]
        diff = "-" if r is ref else cells[0].split(" (")[1].rstrip(")")
        c = r.get("couplings")
        coup = "-" if not c else (
            f"{c['reference']['couplings_per_s']:.0f} ({c['reference']['evals_per_coupling']:.0f} NFE), "
            f"{c['batched_at_reference_tolerance']['couplings_per_s']:.0f}, "
            + ("none" if not c["best_at_equal_accuracy"] else
               f"{c['best_at_equal_accuracy']['couplings_per_s']:.0f} {c['best_at_equal_accuracy']['method']} "
               f"({c['best_at_equal_accuracy']['speedup']:.2f}x)"))
        lines.append(f"| {r['time_scale']:g} | {r['rk45_nfe_per_chunk']} | {r['val_action_mse']:,.0f} | {rk45} | "
                     f"{diff} | {' | '.join(rest)} | {coup} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("-w", "--workspace", type=Path, required=True)
    ap.add_argument("--scales", nargs="+", default=["999", "100", "10", "1"])
    ap.add_argument("--against", default="999", help="the row every score is paired against")
    ap.add_argument("--n-test", type=int, default=200)
    ap.add_argument("--jobs", type=int, default=2, help="evaluations side by side")
    ap.add_argument("--reflow", action="store_true", help="also bench_reflow on every row (minutes each)")
    ap.add_argument("--json", type=Path, help="write the rows, per-seed scores included, here")
    args = ap.parse_args()
    ws = args.workspace.resolve()
    rows = []
    for scale in args.scales:
        row = measure_row(ws, scale, args.n_test, args.jobs)
        if args.reflow:
            row["couplings"] = reflow_bench(ws, scale)
        rows.append(row)
    print(table(rows, args.against))
    if args.json:
        args.json.write_text(json.dumps({"workspace": str(ws), "n_test": args.n_test, "rows": rows}, indent=1))


if __name__ == "__main__":
    sys.path.insert(0, str(REPO))
    main()
