"""What each latency budget buys on Push-T low-dim (issue 26): every policy sefa makes from one
base flow, scored in closed loop and timed at batch 1 in one process.

    python benchmarks/latency_budget.py -w W --base W/rows/ts1 --ddpm W/rows/ddpm [--jobs 2]

Rows, from the base flow BASE (a `cpu`-profile base; any checkpoint a policy loads from) and the
diffusion baseline DDPM (trained with the same preset, `--objective ddpm`):

    base RK45, base Euler-1/2/4        the base flow's own samplers
    reflow-k (k = 1, 2, 4)             a k-step student on the unaligned couplings
    SeFA-k   (k = 1, 2, 4)             a k-step student on the couplings aligned at --eps
    reflowed flow, Euler-1/2/4         a flow trained on the unaligned couplings at uniform t
    DDPM-100, DDIM-10                  the diffusion baseline

The students are built as `sefa reflow` (--windows training windows x --samples noises, RK45 at
the flow's tolerance), `sefa align --eps E` and `sefa distill [--no-align] --steps k
--train-steps N` build them in a workspace, through the same library calls (sefa_model.sefa.reflow,
sefa_model.sefa.alignment, sefa_model.train.loop with sefa_pipelines.stages.student_config); they are made
here because BASE need not be a workspace's train stage (the study's bases were trained on a GPU
and copied back as policies). Students and couplings live in W/budget/, evaluations in W/evals
(`sefa eval --env pusht`, cached): --n-test-students seeds for the students (default 500),
--n-test seeds for the rest (200), scores paired against base RK45 over the seeds both ran.
Latency: `sefa bench latency` over every row in one process (--passes 3, fastest kept). Writes
the table between the `budget-cpu` markers of docs/results/pusht.md, the plot beside it to
docs/results/pusht_latency_budget_cpu.png and the rows with per-seed scores to --json.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
# the `cpu` profile's distill stage (pipelines/pusht_lowdim.yaml)
STUDENT_OVERRIDES = ["training.val_every=1000", "training.checkpoint_every=1000"]
BUDGETS_MS = (1.0, 3.0, 10.0)


@dataclass
class Row:
    name: str
    slug: str
    checkpoint: Path
    made_by: str  # how the policy is made, in sefa's terms
    solver_args: list[str] = field(default_factory=list)
    setting: str = ""  # sefa bench latency's @SETTING ("" = the checkpoint's own)
    student: bool = False
    result: dict = field(default_factory=dict)

    @property
    def target(self) -> str:
        return str(self.checkpoint) + (f"@{self.setting}" if self.setting else "")


def build_students(ws: Path, base: Path, ks: list[int], eps: float, windows: int, samples: int,
                   train_steps: int, threads: int) -> dict[str, Path]:
    """The couplings, their alignment and the 2 x len(ks) students; what exists is reused."""
    import torch

    from sefa_pipelines.stages import FEATURES_DIR, reflowed_flow_config, student_config
    from sefa_model.sefa.alignment import align_to_expert
    from sefa_model.policy.checkpoint import open_policy
    from sefa_model.config import saved_train_config
    from sefa_model.data.couplings import PairSource, aligned_attrs
    from sefa_model.policy.artifact import Policy
    from sefa_model.sefa.reflow import CouplingConfig, generate_couplings
    from sefa_model.train.loop import train

    torch.set_num_threads(threads)
    store, out, features = ws / "dataset.zarr", ws / "budget", ws / FEATURES_DIR
    couplings, aligned = out / "couplings.zarr", out / f"aligned_eps{eps:g}.zarr"
    ckpt, meta, _ = open_policy(base)
    made = lambda group: (group / ".zgroup").exists() or (group / "zarr.json").exists()  # zarr 2 or 3
    if not made(couplings):
        started = time.perf_counter()
        summary = generate_couplings(Policy.load(ckpt, device="cpu"), store, couplings,
                                     CouplingConfig(samples_per_window=samples, max_windows=windows),
                                     source=str(base), features_cache=features)
        print(f"couplings: {summary['n']} ({summary['nfe_per_solve']:.0f} NFE per solve) in {time.perf_counter() - started:.0f} s", flush=True)
    if not made(aligned):
        align_to_expert(ckpt, store, couplings, aligned, eps, device="cpu", features_cache=features)
    attrs = aligned_attrs(aligned)
    replaced = attrs["n_replaced"]
    print(f"aligned at eps {eps:g}: {attrs['fraction_replaced']:.1%} of the couplings replaced", flush=True)
    base_cfg = saved_train_config(meta["train_config"], source=str(ckpt / "config.json"))
    students = {}
    for k in ks:
        for align in (False, True):
            slug = f"{'sefa' if align else 'reflow'}_k{k}"
            run = out / slug
            students[slug] = run
            if (run / "checkpoints" / "latest" / "config.json").exists():
                continue
            cfg = student_config(base_cfg, STUDENT_OVERRIDES + ["training.device=cpu"],
                                 train_steps=train_steps, steps=k)
            source = (PairSource.aligned(aligned, "sefa_one_step" if replaced else "reflow_one_step")
                      if align else PairSource.couplings(couplings, "reflow_one_step"))
            started = time.perf_counter()
            train(cfg, run, store, couplings=source, init_from=ckpt, features_cache=features)
            print(f"{slug}: trained in {time.perf_counter() - started:.0f} s", flush=True)
    # the reflowed flow (uniform t, as `sefa reflow --iters 2` trains it), for its Euler-k rows
    run = students["reflowed_flow"] = out / "reflowed_flow"
    if not (run / "checkpoints" / "latest" / "config.json").exists():
        cfg = reflowed_flow_config(base_cfg, STUDENT_OVERRIDES + ["training.device=cpu"], train_steps)
        train(cfg, run, store, couplings=PairSource.couplings(couplings, "reflow"), init_from=ckpt,
              features_cache=features)
    return students


def rows(base: Path, ddpm: Path, students: dict[str, Path], ks: list[int], eps: float,
         windows: int, samples: int, train_steps: int, replaced: float) -> list[Row]:
    # the checkpoint's own sampler (RK45 at its recorded tolerance): `sefa eval BASE --env pusht`
    out = [Row("base flow, RK45", "base_rk45", base, "the base flow", [], "rk45")]
    for k in (1, 2, 4):
        out.append(Row(f"base flow, Euler-{k}", f"base_euler{k}", base, "the base flow",
                       ["--solver", "euler", "--steps", str(k)], f"euler-{k}"))
    couplings = f"`sefa reflow` ({windows} windows x K = {samples})"
    for k in ks:
        out.append(Row(f"reflow-{k} (student, no alignment)", f"reflow_k{k}", students[f"reflow_k{k}"],
                       f"{couplings}; `sefa distill --no-align --steps {k} --train-steps {train_steps}`",
                       student=True))
        out.append(Row(f"SeFA-{k} (student, eps {eps:g})", f"sefa_k{k}", students[f"sefa_k{k}"],
                       f"{couplings}; `sefa align --eps {eps:g}` ({replaced:.1%} replaced); `sefa distill --steps {k} "
                       f"--train-steps {train_steps}`", student=True))
    for k in (1, 2, 4):
        out.append(Row(f"reflowed flow, Euler-{k}", f"reflowed_euler{k}", students["reflowed_flow"],
                       f"{couplings}; the reflowed flow of `sefa reflow --iters 2 --train-steps "
                       f"{train_steps}` (uniform t)", ["--solver", "euler", "--steps", str(k)],
                       f"euler-{k}"))  # a flow sampled with k steps, as the base's Euler-k rows
    out += [Row("diffusion, DDPM-100", "ddpm100", ddpm, "`sefa train <preset> --objective ddpm`",
                ["--solver", "ddpm", "--steps", "100"], "ddpm-100"),
            Row("diffusion, DDIM-10", "ddim10", ddpm, "`sefa train <preset> --objective ddpm`",
                ["--solver", "ddim", "--steps", "10"], "ddim-10")]
    return out


def sefa_json(ws: Path, *args: str) -> object:
    done = subprocess.run([sys.executable, "-m", "sefa_cli.main", *args, "--json", "-w", str(ws)],
                          cwd=REPO, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"`sefa {' '.join(args)}` failed: {done.stderr.strip().splitlines()[-1:]}")
    return json.loads(done.stdout)


def evaluate(ws: Path, row: Row, n_test: int) -> None:
    r = sefa_json(ws, "eval", str(row.checkpoint), "--env", "pusht", "--n-test", str(n_test),
                  *row.solver_args, "--threads", "1")[0]
    log = json.loads((ws / r["eval_log"]).read_text())
    row.result = {"score": r["test/mean_score"], "success_rate": r["test/success_rate"],
                  "n_test": r["n_test"], "nfe": r["nfe"], "kind": r["kind"], "solver": r["solver"],
                  "per_seed": [p["score"] for p in sorted(log["per_seed"], key=lambda p: p["seed"])]}


def best_under(table: list[Row], timing: dict[str, dict], budget_ms: float) -> Row | None:
    fits = [r for r in table if r.slug in timing and timing[r.slug]["p50_ms"] <= budget_ms]
    return max(fits, key=lambda r: r.result["score"], default=None)


def render(table: list[Row], timing: dict[str, dict], latency: dict, base_name: str) -> str:
    from reflow_rounds import paired
    from sefa_data.bench.throughput import machine_summary

    ref = next(r for r in table if r.slug == "base_rk45")
    lines = [f"Base flow: `{base_name}`. Latency: `sefa bench latency` on {latency.get('device')} "
             f"({machine_summary(latency['machine'])}), batch 1, p50 (p90), the fastest of "
             f"{latency.get('passes')} passes over all rows in one process. Score: Push-T test seeds "
             "from 100000, 300 steps; differences paired over the seeds both rows ran.", "",
             "| policy | NFE | latency p50 (p90), ms | score | seeds | success | - base RK45 (paired) | made by |",
             "|---|---|---|---|---|---|---|---|"]
    for r in sorted(table, key=lambda r: timing.get(r.slug, {}).get("p50_ms", 1e9)):
        t = timing.get(r.slug)
        d, se = paired(r.result["per_seed"], ref.result["per_seed"])
        diff = "-" if r is ref else f"{d:+.3f} ± {se:.3f}"
        lat = f"{t['p50_ms']:.3g} ({t['p90_ms']:.3g})" if t else "-"
        lines.append(f"| {r.name} | {r.result['nfe']} | {lat} | {r.result['score']:.3f} | "
                     f"{r.result['n_test']} | {r.result['success_rate']:.1%} | {diff} | {r.made_by} |")
    lines += ["", "Best score within each budget (p50):", ""]
    for budget in BUDGETS_MS:
        b = best_under(table, timing, budget)
        lines.append(f"- **{budget:g} ms**: " + ("nothing fits" if b is None else
                     f"{b.name}, {b.result['score']:.3f} ({timing[b.slug]['p50_ms']:.3g} ms)"))
    return "\n".join(lines)


def plot(table: list[Row], timing: dict[str, dict], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colors = {"base": "tab:blue", "refl": "tab:orange", "sefa": "tab:green", "ddpm": "tab:gray",
              "ddim": "tab:gray", "reflowed": "tab:purple"}
    fig, ax = plt.subplots(figsize=(7.5, 4.8), dpi=120)
    for r in table:
        if r.slug not in timing:
            continue
        x, y = timing[r.slug]["p50_ms"], r.result["score"]
        ax.scatter(x, y, color=colors.get(r.slug.split("_")[0], colors[r.slug[:4]]), zorder=3)
        ax.annotate(r.name.split(" (")[0], (x, y), fontsize=7, xytext=(4, 3), textcoords="offset points")
    for budget in BUDGETS_MS:
        ax.axvline(budget, color="k", lw=0.6, ls=":")
    ax.set_xscale("log")
    ax.set_xlabel("batch-1 latency p50, ms (log scale; dotted: 1, 3, 10 ms budgets)")
    ax.set_ylabel("Push-T score")
    ax.set_title("Push-T low-dim: score against latency, one base flow")
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(out)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("-w", "--workspace", type=Path, required=True, help="holds dataset.zarr")
    ap.add_argument("--base", type=Path, required=True)
    ap.add_argument("--ddpm", type=Path, required=True)
    ap.add_argument("--k", type=int, nargs="+", default=[1, 2, 4])
    ap.add_argument("--eps", type=float, default=0.05)
    ap.add_argument("--windows", type=int, default=3000)
    ap.add_argument("--samples", type=int, default=10)
    ap.add_argument("--train-steps", type=int, default=2000)
    ap.add_argument("--n-test-students", type=int, default=500)
    ap.add_argument("--n-test", type=int, default=200)
    ap.add_argument("--jobs", type=int, default=2, help="evaluations side by side")
    ap.add_argument("--threads", type=int, default=2, help="torch threads while building")
    ap.add_argument("--results", type=Path, default=REPO / "docs" / "results" / "pusht.md")
    ap.add_argument("--plot", type=Path, default=REPO / "docs" / "results" / "pusht_latency_budget_cpu.png")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    ws, base, ddpm = args.workspace.resolve(), args.base.resolve(), args.ddpm.resolve()

    students = build_students(ws, base, args.k, args.eps, args.windows, args.samples,
                              args.train_steps, args.threads)
    from sefa_model.data.couplings import aligned_attrs

    replaced = aligned_attrs(ws / "budget" / f"aligned_eps{args.eps:g}.zarr")["fraction_replaced"]
    table = rows(base, ddpm, students, args.k, args.eps, args.windows, args.samples,
                 args.train_steps, replaced)
    with ThreadPoolExecutor(args.jobs) as pool:
        list(pool.map(lambda r: evaluate(ws, r, args.n_test_students if r.student else args.n_test), table))
    latency = sefa_json(ws, "bench", "latency", *[r.target for r in table], "--device", "cpu",
                        "--passes", "3", "--max-seconds", "10")
    timing = {r.slug: t for r, t in zip(table, latency["rows"])}
    report = render(table, timing, latency, str(base.relative_to(ws)) if base.is_relative_to(ws) else str(base))
    from pusht_study import write_between_markers

    write_between_markers(args.results, "budget-cpu", report)
    plot(table, timing, args.plot)
    print(report)
    if args.json:
        args.json.write_text(json.dumps({
            "base": str(base), "ddpm": str(ddpm), "latency": latency,
            "rows": [{"name": r.name, "slug": r.slug, "made_by": r.made_by, "target": r.target,
                      **r.result, "timing": timing.get(r.slug)} for r in table]}, indent=1))


if __name__ == "__main__":
    sys.path.insert(0, str(REPO))
    main()
