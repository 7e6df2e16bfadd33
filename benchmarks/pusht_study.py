"""The Push-T accuracy-versus-latency study (docs/results/pusht.md), in one command:

    python benchmarks/pusht_study.py --profile cpu     # 2 CPU cores (two 30,000-step trainings)
    python benchmarks/pusht_study.py --profile full    # a GPU, Diffusion Policy's training lengths

--data DIR names the folder holding pusht_cchi_v7_replay.zarr, Diffusion Policy's published
Push-T training set (its pusht.zip unpacks to pusht/pusht_cchi_v7_replay.zarr: --data pusht).

It runs the `sefa` commands of every row in one workspace (runs/study-<profile>), in an order
that reuses cached stages, and records each row's commands next to its numbers:

    diffusion baseline    sefa train <train preset> --objective ddpm --out W/ddpm; DDPM-100, DDIM-10
    base rectified flow   sefa run <pipeline preset> (the train stage); RK45 and Euler-1
    reflow, no alignment  sefa reflow --iters 1|2; sefa distill --no-align
    SeFA one-step         sefa align --eps E; sefa distill     for E in 0.02, 0.05, 0.1, 0.2

A distilled policy is copied out of W/distill (W/rows/<row>) before the next variant replaces
it. Every policy is evaluated on the same Push-T test seeds (`sefa eval --env pusht`), on
the store's validation windows (`sefa eval --offline`: action MSE, NFE) and, at the end and in
one process, for batch-1 latency (`sefa bench latency`). One-step rows are rolled out on 500
seeds (from 100000) and multi-step rows on 200 (--n-test-one-step, --n-test-multi-step);
differences are paired over the seeds both rows ran. Then (unless --no-rounds) it runs the
reflow-rounds study and its eps and K sweeps (benchmarks/reflow_rounds.py) in W-rounds, on the
same base flow. Finished rows are kept in
W/study.json, so an interrupted study continues where it stopped (--redo-latency re-times).
The table, the goal ratios and the plot go between this profile's markers in its results page
(docs/results/pusht.md for `cpu`, docs/results/gpu.md for `full`) and to
pusht_score_vs_latency_<profile>.png beside that page.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from sefa_data import atomic
from sefa_data.bench.throughput import DEFAULT_DATA_DIR

REPO = Path(__file__).resolve().parents[1]
PUSHT_FILE = "pusht_cchi_v7_replay.zarr"
# the store as the reader has it: pusht.zip, Diffusion Policy's published training set, unpacks
# to this path (the results page says where to get it); the table names it, not --data's path
PUSHT_PUBLISHED = f"pusht/{PUSHT_FILE}"
PROFILES = {"cpu": ("pipelines/pusht_lowdim.yaml", "pipelines/pusht_lowdim_train.yaml"),
            "full": ("pipelines/pusht_lowdim_full.yaml", "pipelines/pusht_lowdim_train_full.yaml")}
# each profile's results page, which holds its `study:<profile>` markers
RESULTS = {"cpu": REPO / "docs" / "results" / "pusht.md", "full": REPO / "docs" / "results" / "gpu.md"}
EPS = (0.02, 0.05, 0.1, 0.2)
# the reflow-rounds study and its sweeps (docs/results/pusht.md) at each profile's budget
ROUNDS_ARGS = {
    "cpu": ["--rounds", "3", "--windows", "2000", "--samples", "5", "--flow-steps", "2000",
            "--student-steps", "2000", "--eps", "0.05", "--n-test", "500", "--base-n-test", "200",
            "--eps-sweep", "0.1", "0.2", "--k-sweep", "2", "10"],
    "full": ["--rounds", "3", "--windows", "5000", "--samples", "10", "--flow-steps", "20000",
             "--student-steps", "20000", "--eps", "0.05", "--n-test", "500", "--base-n-test", "200",
             "--eps-sweep", "0.02", "0.1", "0.2", "--k-sweep", "2", "20"],
}


@dataclass
class Row:
    name: str
    slug: str
    prepare: list[list[str]]  # sefa commands (without `-w W`) that make the policy
    checkpoint: str  # relative to W: a run dir, or rows/<slug> for a snapshot of W/distill
    solver: str | None = None
    steps: int | None = None
    snapshot: bool = False
    result: dict = field(default_factory=dict)

    @property
    def setting(self) -> str:
        return "" if self.solver is None else f"{self.solver}" + ("" if self.steps is None else f"-{self.steps}")

    @property
    def multi_step(self) -> bool:
        return self.solver in ("rk45", "ddpm", "ddim")

    def solver_args(self) -> list[str]:
        out = [] if self.solver is None else ["--solver", self.solver]
        return out + ([] if self.steps is None else ["--steps", str(self.steps)])


def rows(pipeline: str, train_preset: str) -> list[Row]:
    """In running order: each variant's commands assume the workspace the previous ones left."""
    out = [
        Row("SeFA one-step, eps 0.05", "sefa_eps0.05", [["run", pipeline]], "rows/sefa_eps0.05", snapshot=True),
        Row("base flow, RK45", "base_rk45", [["run", pipeline]], "train", "rk45"),
        Row("base flow, Euler-1", "base_euler1", [["run", pipeline]], "train", "euler", 1),
    ]
    for eps in EPS:
        if eps != 0.05:
            out.append(Row(f"SeFA one-step, eps {eps:g}", f"sefa_eps{eps:g}",
                           [["reflow", "--iters", "1"], ["align", "--eps", f"{eps:g}"], ["distill", "--align"]],
                           f"rows/sefa_eps{eps:g}", snapshot=True))
    for it in (1, 2):
        out.append(Row(f"reflow x{it}, one step, no alignment", f"reflow{it}_noalign",
                       [["reflow", "--iters", str(it)], ["distill", "--no-align"]],
                       f"rows/reflow{it}_noalign", snapshot=True))
    ddpm = [["train", train_preset, "--objective", "ddpm", "--out", "{W}/ddpm"]]
    out += [Row("diffusion (DDPM-100)", "ddpm100", ddpm, "ddpm", "ddpm", 100),
            Row("diffusion (DDIM-10)", "ddim10", ddpm, "ddpm", "ddim", 10)]
    return out


class Study:
    def __init__(self, workspace: Path, n_test: tuple[int, int], dry_run: bool):
        self.w, self.n_test, self.dry_run = workspace, n_test, dry_run
        self.state_path = workspace / "study.json"
        self.state = json.loads(self.state_path.read_text()) if self.state_path.exists() else {}

    def save(self) -> None:
        atomic.write_json(self.state_path, self.state)

    def sefa(self, args: list[str], capture: bool = False) -> str:
        args = [a.replace("{W}", str(self.w)) for a in args]
        if "-w" not in args:
            args += ["-w", str(self.w)]
        print("$ sefa " + " ".join(args), flush=True)
        if self.dry_run:
            return "[{}]" if capture else ""
        done = subprocess.run([sys.executable, "-m", "sefa_cli.main", *args], cwd=REPO, text=True,
                              stdout=subprocess.PIPE if capture else None)
        if done.returncode != 0:
            raise SystemExit(f"study: `sefa {' '.join(args)}` failed (exit {done.returncode})")
        return done.stdout or ""

    def make(self, row: Row) -> None:
        if (self.w / row.checkpoint / "checkpoints" / "latest").exists():
            return  # made earlier (a snapshot is copied only once its commands succeeded)
        started = time.perf_counter()
        for cmd in row.prepare:
            self.sefa(cmd)
        if row.snapshot and not self.dry_run:
            dest = self.w / row.checkpoint
            shutil.rmtree(dest, ignore_errors=True)
            shutil.copytree(self.w / "distill", dest)
        self.state.setdefault("build_seconds", {})[row.slug] = time.perf_counter() - started

    def evaluate(self, row: Row) -> None:
        if row.slug in self.state and "score" in self.state[row.slug]:
            row.result = self.state[row.slug]
            return
        ckpt = str(self.w / row.checkpoint)
        n_test = self.n_test[1] if row.multi_step else self.n_test[0]
        sim = json.loads(self.sefa(["eval", ckpt, "--env", "pusht", "--n-test", str(n_test),
                                    *row.solver_args(), "--json"], capture=True) or "[{}]")[0]
        off = json.loads(self.sefa(["eval", ckpt, "--offline", *row.solver_args(), "--json"],
                                   capture=True) or "[{}]")[0]
        row.result = {"score": sim.get("test/mean_score"), "success_rate": sim.get("test/success_rate"),
                      "n_test": sim.get("n_test"), "kind": sim.get("kind"), "solver": sim.get("solver"),
                      "val_action_mse": off.get("action_mse"), "nfe": off.get("nfe"),
                      "spread_ratio": off.get("spread_ratio"), "eval_seconds": sim.get("seconds"),
                      "eval_log": sim.get("eval_log")}
        if not self.dry_run:
            self.state[row.slug] = row.result
            self.save()

    def latency(self, table: list[Row], redo: bool) -> dict:
        if "latency" in self.state and not redo:
            return self.state["latency"]
        targets = [str(self.w / r.checkpoint) + (f"@{r.setting}" if r.setting else "") for r in table]
        out = json.loads(self.sefa(["bench", "latency", *targets, "--device", "auto", "--passes", "3",
                                    "--max-seconds", "10", "--json"],
                                   capture=True) or "{}")
        out = out if isinstance(out, dict) else {}
        if not self.dry_run:
            self.state["latency"] = out
            self.save()
        return out


# ----------------------------------------------------------------------------- the report


def _timing(row: Row, latency: dict) -> dict:
    """The `sefa bench latency` row of this study row (matched by checkpoint and setting)."""
    for r in latency.get("rows", []):
        if r["target"].split("@")[0].endswith(row.checkpoint) and r["target"].endswith(
                f"@{row.setting}" if row.setting else row.checkpoint):
            return r
    return {}


# the order: the baselines, then the one-step policies from plain reflow to SeFA
DISPLAY = ("ddpm100", "ddim10", "base_rk45", "base_euler1", "reflow1_noalign", "reflow2_noalign",
           *(f"sefa_eps{e:g}" for e in EPS))


def paired_difference(a: Row, b: Row) -> tuple[float, float | None]:
    """Mean score difference a - b and its standard error, paired over the same test seeds
    (the seeds' difficulty cancels): both start at seed 100000, the longer is cut to the
    shorter's seeds; no error without per-seed scores."""
    from reflow_rounds import paired

    sa, sb = a.result.get("per_seed"), b.result.get("per_seed")
    if not sa or not sb:
        return a.result["score"] - b.result["score"], None
    return paired(sa, sb)


def goals(table: list[Row], latency: dict) -> list[tuple[str, str, dict[str, tuple]]]:
    """The acceptance goals, each measured for every SeFA row of this run:
    [(goal, target, {row name: (value, standard error or None, met)})]."""
    by = {r.slug: r for r in table}
    sefa = [r for r in table if r.slug.startswith("sefa")]
    t_ddpm = _timing(by["ddpm100"], latency)
    lat_ddpm, lat_fwd, vs_rk45 = {}, {}, {}
    vs_reflow: dict[int, dict] = {1: {}, 2: {}}
    for row in sefa:
        t = _timing(row, latency)
        if t and t_ddpm:
            r = t["p50_ms"] / t_ddpm["p50_ms"]
            lat_ddpm[row.name] = (r, None, r <= 0.02)
        if t:
            r = t["p50_ms"] / t["forward_ms"]
            lat_fwd[row.name] = (r, None, r <= 1.2)
        d, se = paired_difference(row, by["base_rk45"])
        vs_rk45[row.name] = (d, se, d >= -0.02)
        for it in (1, 2):
            d, se = paired_difference(row, by[f"reflow{it}_noalign"])
            # issue 11: above plain reflow by at least 2 paired standard errors, not noise
            vs_reflow[it][row.name] = (d, se, d > 0 if se is None else d >= 2 * se)
    return [("latency / DDPM-100 latency", "<= 0.02", lat_ddpm),
            ("latency / its bare forward pass", "<= 1.2", lat_fwd),
            ("score - base flow RK45 score", ">= -0.02", vs_rk45),
            ("score - reflow x1 one-step (no alignment) score", ">= 2 s.e.", vs_reflow[1]),
            ("score - reflow x2 one-step (no alignment) score", ">= 2 s.e.", vs_reflow[2])]


def render_report(profile: str, table: list[Row], latency: dict, pipeline: str, train_preset: str,
                  plot_name: str) -> str:
    from sefa_data.bench.throughput import machine_summary

    machine = machine_summary(latency["machine"]) if latency.get("machine") else "this machine"
    n_one = max((r.result.get("n_test") or 0) for r in table if not r.multi_step)
    n_multi = max((r.result.get("n_test") or 0) for r in table if r.multi_step)
    lines = [f"Profile `{profile}`: `{pipeline}` (base policy `{train_preset}`), "
             f"Push-T test seeds from 100000, 300 steps each: {n_one} for one-step rows, {n_multi} "
             "for multi-step rows (the seeds column), differences paired over the seeds both ran. "
             f"Latency: `sefa bench latency` on {latency.get('device', 'cpu')} ({machine}), "
             f"batch 1, p50 (p90) over up to {latency.get('calls', '?')} calls after "
             f"{latency.get('warmup', '?')} warm-up calls, the fastest of {latency.get('passes', 1)} "
             "passes over all rows in one process.",
             "",
             f"W is the workspace, made by `sefa ingest {PUSHT_PUBLISHED} "
             f"--fps 10 --key keypoint --key state --key action -w W` and `sefa run {pipeline} -w W` "
             "(base flow, reflow x1, align, distill); each row's commands then run in W (`-w W` left "
             "out), and the study runs them in an order that reuses cached stages.",
             "",
             "| policy | NFE | latency p50 (p90), ms | x bare forward | score | seeds | success | val action MSE (px²) | commands (in W) |",
             "|---|---|---|---|---|---|---|---|---|"]
    order = {slug: i for i, slug in enumerate(DISPLAY)}
    for row in sorted(table, key=lambda r: order.get(r.slug, len(order))):
        r, t = row.result, _timing(row, latency)
        cmds = "; ".join("sefa " + " ".join(c).replace("{W}/", "") for c in row.prepare)
        cmds += f"; sefa eval {row.checkpoint} --env pusht {' '.join(row.solver_args())}".rstrip()
        lat = f"{t['p50_ms']:.3g} ({t['p90_ms']:.3g})" if t else "-"
        rel = f"{t['p50_ms'] / t['forward_ms']:.2f}" if t else "-"
        lines.append(f"| {row.name} | {r.get('nfe')} | {lat} | {rel} | {r['score']:.3f} | "
                     f"{r.get('n_test')} | {r['success_rate']:.1%} | {r['val_action_mse']:,.0f} | `{cmds}` |")
    sefa = [f"SeFA one-step, eps {e:g}" for e in EPS]
    lines += ["", "Goals, for each SeFA row (ratios and differences of this run; score differences "
              "are means over the same seeds ± their paired standard error):", "",
              "| SeFA one-step ... | target | " + " | ".join(n.split(", ")[1] for n in sefa) + " |",
              "|---|---|" + "---|" * len(sefa)]
    for name, target, cells in goals(table, latency):
        row = []
        for n in sefa:
            if n not in cells:
                row.append("-")
                continue
            value, se, met = cells[n]
            err = "" if se is None else f" ± {se:.3f}"
            row.append(f"{value:+.3f}{err} {'yes' if met else '**no**'}")
        lines.append(f"| {name} | {target} | " + " | ".join(row) + " |")
    lines += ["", f"![score against latency]({plot_name})"]
    return "\n".join(lines)


def load_per_seed(row: Row, workspace: Path) -> None:
    """Per-seed scores from the row's eval_log.json (written by `sefa eval --env pusht`)."""
    if row.result.get("per_seed"):
        return
    suffix = f"_{row.setting}" if row.setting else ""
    # `sefa eval --json` names the log relative to the workspace, not to this process's cwd
    log = workspace / (row.result.get("eval_log") or Path(row.checkpoint) / f"eval_pusht{suffix}" / "eval_log.json")
    if log.exists():
        row.result["per_seed"] = [r["score"] for r in json.loads(log.read_text())["per_seed"]]


def write_between_markers(path: Path, profile: str, text: str) -> None:
    """Replace this profile's generated block in `path`, keeping the prose around it."""
    begin, end = f"<!-- study:{profile}:begin -->", f"<!-- study:{profile}:end -->"
    old = path.read_text() if path.exists() else f"# Results\n\n{begin}\n{end}\n"
    if begin not in old:
        old += f"\n{begin}\n{end}\n"
    head, rest = old.split(begin, 1)
    tail = rest.split(end, 1)[1]
    atomic.write_text(path, f"{head}{begin}\n{text}\n{end}{tail}")


def plot_scores(table: list[Row], latency: dict, out: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colors = {"ddpm": "tab:gray", "ddim": "tab:gray", "base": "tab:blue", "refl": "tab:orange",
              "sefa": "tab:green"}
    fig, ax = plt.subplots(figsize=(7, 4.5), dpi=120)
    for row in table:
        t = _timing(row, latency)
        if not t:
            continue
        ax.scatter(t["p50_ms"], row.result["score"], color=colors[row.slug[:4]], zorder=3)
        ax.annotate(row.name, (t["p50_ms"], row.result["score"]), fontsize=7,
                    xytext=(4, 3), textcoords="offset points")
    ax.set_xscale("log")
    ax.set_xlabel("batch-1 latency, p50 (ms, log scale)")
    ax.set_ylabel("Push-T score (500 seeds one-step, 200 multi-step)")
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--profile", choices=sorted(PROFILES), default="cpu")
    ap.add_argument("--workspace", type=Path, default=None, help="default: runs/study-<profile>")
    ap.add_argument("--n-test-one-step", type=int, default=500)
    ap.add_argument("--n-test-multi-step", type=int, default=200)
    ap.add_argument("--base-from", type=Path, default=None, metavar="CKPT",
                    help="a kept checkpoint of the train preset's own run (the budget curve's "
                         "step_30000), continued as the train stage instead of training again")
    ap.add_argument("--rounds", action=argparse.BooleanOptionalAction, default=True,
                    help="then the reflow-rounds study and its sweeps, in W-rounds (default: yes)")
    ap.add_argument("--results", type=Path, default=None,
                    help="the page with this profile's markers (default: its page in docs/results/)")
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA_DIR,
                    help=f"the folder holding {PUSHT_FILE} (Diffusion Policy's pusht.zip unpacks to pusht/)")
    ap.add_argument("--redo-latency", action="store_true", help="re-time every row (a quiet machine)")
    ap.add_argument("--dry-run", action="store_true", help="print the commands only")
    args = ap.parse_args()

    pipeline, train_preset = PROFILES[args.profile]
    workspace = (args.workspace or REPO / "runs" / f"study-{args.profile}").resolve()
    workspace.mkdir(parents=True, exist_ok=True)
    study = Study(workspace, (args.n_test_one_step, args.n_test_multi_step), args.dry_run)
    if not (workspace / "dataset.zarr").exists():
        study.sefa(["ingest", str(args.data / PUSHT_FILE), "--fps", "10", "--key", "keypoint", "--key", "state",
                    "--key", "action", "-w", str(workspace)])
    if args.base_from is not None and not args.dry_run:
        from reflow_rounds import seed_base

        seed_base(workspace, args.base_from.resolve(), pipeline=REPO / pipeline)
    table = rows(pipeline, train_preset)
    for row in table:
        study.make(row)
        study.evaluate(row)
    latency = study.latency(table, args.redo_latency)
    if args.dry_run:
        return
    results = args.results or RESULTS[args.profile]
    plot = results.parent / f"pusht_score_vs_latency_{args.profile}.png"  # beside its page
    for row in table:
        load_per_seed(row, workspace)
    report = render_report(args.profile, table, latency, pipeline, train_preset, plot.name)
    write_between_markers(results, args.profile, report)
    plot_scores(table, latency, plot, f"Push-T low-dim, profile {args.profile}")
    print(report)
    if args.rounds:
        rounds = workspace.with_name(workspace.name + "-rounds")
        cmd = [sys.executable, str(REPO / "benchmarks" / "reflow_rounds.py"), "-w", str(rounds),
               *ROUNDS_ARGS[args.profile], "--base-from", str(workspace / "train" / "checkpoints" / "latest"), "--data", str(args.data),
               "--plot", str(results.parent / f"reflow_rounds_{args.profile}.png")]
        print("$ " + " ".join(cmd), flush=True)
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))}
        if subprocess.run(cmd, cwd=REPO, env=env).returncode != 0:
            raise SystemExit("study: the reflow-rounds study failed")


if __name__ == "__main__":
    sys.path.insert(0, str(REPO))
    main()
