"""SeFA on Meta-World, task by task (docs/metaworld.md), resumable:

    python benchmarks/metaworld_study.py --tasks easy             # a difficulty group
    python benchmarks/metaworld_study.py --tasks reach push hard  # tasks and groups mixed
    python benchmarks/metaworld_study.py --report-only            # the tables of what is done

For each task, in its own workspace R/<task> (R: --root, default runs/metaworld-study):

    sefa collect R/<task>/demos_<seed>.hdf5 --env metaworld:<task> --episodes N --seed S
        (scripted expert; seeds from 0, more attempted until --demos successful ones are kept)
    sefa ingest <the demo files> -w W
    sefa run pipelines/metaworld.yaml -w W           base flow, reflow x1, align, one-step student
    sefa train pipelines/metaworld_train.yaml --objective ddpm --out W/ddpm -w W
    sefa eval <row> --env metaworld:<task> --n-test N [--solver ...] -w W
    sefa bench latency <every row> -w W

Rows: base flow RK45, base flow Euler-1, the SeFA one-step student, the diffusion baseline
DDIM-10, each on the same test seeds (from 100000; the demonstrations use seeds from 0). Each
task's results go into R/results.json as soon as a row is done (the stages and evaluations are
cached in the workspace too), so an interrupted study continues where it stopped. The report:
per task, every row's success rate ± its standard error and p50 latency; per difficulty group,
each row's success over all the group's episodes ± standard error, and the student minus
RK45 paired over (task, seed) ± its standard error, with the latency ratio student / RK45.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
PIPELINE = "pipelines/metaworld.yaml"
TRAIN_PRESET = "pipelines/metaworld_train.yaml"
START_SEED = 100000


@dataclass(frozen=True)
class Row:
    slug: str
    name: str
    checkpoint: str  # relative to the task's workspace
    solver: str | None = None
    steps: int | None = None

    @property
    def setting(self) -> str:
        return "" if self.solver is None else self.solver + ("" if self.steps is None else f"-{self.steps}")

    def solver_args(self) -> list[str]:
        out = [] if self.solver is None else ["--solver", self.solver]
        return out + ([] if self.steps is None else ["--steps", str(self.steps)])


ROWS = (Row("base_rk45", "base flow, RK45", "train", "rk45"),
        Row("base_euler1", "base flow, Euler-1", "train", "euler", 1),
        Row("sefa", "SeFA one-step", "distill"),
        Row("ddim10", "diffusion (DDIM-10)", "ddpm", "ddim", 10))
STUDENT, TEACHER = "sefa", "base_rk45"


class Study:
    def __init__(self, root: Path, demos: int, n_test: int, dry_run: bool,
                 pipeline: str = PIPELINE, train_preset: str = TRAIN_PRESET):
        self.root, self.demos, self.n_test, self.dry_run = root, demos, n_test, dry_run
        self.pipeline, self.train_preset = pipeline, train_preset
        self.path = root / "results.json"
        self.results = json.loads(self.path.read_text()) if self.path.exists() else {}
        for task, entry in self.results.items():  # rows kept before the kind was recorded
            for row in entry.get("rows", {}).values():
                log = root / task / row.get("eval_log", "-")
                if "kind" not in row and log.is_file():
                    row["kind"] = json.loads(log.read_text()).get("kind")

    def save(self) -> None:
        from sefa_data import atomic

        if not self.dry_run:
            atomic.write_json(self.path, self.results)

    def sefa(self, args: list[str], ws: Path | None = None, capture: bool = False) -> str:
        args = [*args, *(["-w", str(ws)] if ws is not None else [])]
        print("$ sefa " + " ".join(args), flush=True)
        if self.dry_run:
            return "{}" if capture else ""
        done = subprocess.run([sys.executable, "-m", "sefa_cli.main", *args], cwd=REPO, text=True,
                              stdout=subprocess.PIPE if capture else None)
        if done.returncode != 0:
            raise SystemExit(f"study: `sefa {' '.join(args)}` failed (exit {done.returncode})")
        return done.stdout or ""

    def build(self, task: str, extra: tuple[str, ...] = ()) -> Path:
        """The task's workspace: its demonstrations, the pipeline, the diffusion baseline
        (each kept: cached stages return at once). `extra`: options for every training."""
        ws = self.root / task
        ws.mkdir(parents=True, exist_ok=True)
        entry = self.results.setdefault(task, {"rows": {}})
        if "demos" not in entry:
            entry.update(self.collect(task, ws))
            self.save()
        if not (ws / "dataset.zarr").exists():
            self.sefa(["ingest", *entry["demo_files"]], ws)
        self.sefa(["run", self.pipeline, *extra], ws)
        if not (ws / "ddpm" / "checkpoints" / "latest").exists():
            self.sefa(["train", self.train_preset, "--objective", "ddpm", "--out", str(ws / "ddpm"),
                       *extra], ws)
        return ws

    def run_task(self, task: str) -> None:
        ws = self.build(task)
        entry = self.results[task]
        for row in ROWS:
            if row.slug in entry["rows"]:
                continue
            out = json.loads(self.sefa(["eval", str(ws / row.checkpoint), "--env",
                                        f"metaworld:{task}", "--n-test", str(self.n_test),
                                        *row.solver_args(), "--json"], ws, capture=True))
            if self.dry_run:
                continue
            log = json.loads((ws / out[0]["eval_log"]).read_text())
            entry["rows"][row.slug] = {
                "success_rate": log["test/success_rate"], "n_test": log["n_test"],
                "nfe": log["nfe"], "solver": log["solver"], "eval_log": out[0]["eval_log"],
                "kind": log["kind"],
                "per_seed": [int(p["success"]) for p in log["per_seed"]]}
            self.save()
        if "latency" not in entry:
            targets = [str(ws / r.checkpoint) + (f"@{r.setting}" if r.setting else "") for r in ROWS]
            lat = json.loads(self.sefa(["bench", "latency", *targets, "--device", "auto",
                                        "--max-seconds", "5", "--json"], ws, capture=True))
            if not self.dry_run:
                entry["latency"] = {r.slug: next(x["p50_ms"] for x in lat["rows"] if x["target"] == t)
                                    for r, t in zip(ROWS, targets)}
                self.save()
        if not self.dry_run:
            entry["training_steps"] = training_steps(ws)
            self.save()

    def collect(self, task: str, ws: Path) -> dict:
        """--demos successful scripted demonstrations, attempting more seeds after failures
        (at most 3 times as many attempts as demos)."""
        files, kept, failed, seed = [], 0, [], 0
        while kept < self.demos and seed < 3 * self.demos:
            want = self.demos - kept
            out = ws / f"demos_{seed}.hdf5"
            s = json.loads(self.sefa(["collect", str(out), "--env", f"metaworld:{task}",
                                      "--episodes", str(want), "--seed", str(seed), "--json"],
                                     capture=True))
            if self.dry_run:
                return {"demos": self.demos, "demo_files": [str(out)]}
            files.append(str(out))
            kept += s["successful"]
            failed += s["failed_seeds"]
            seed += want
        if kept == 0:
            raise SystemExit(f"study: the scripted expert of {task} succeeded on none of "
                             f"seeds 0..{seed - 1}")
        return {"demos": kept, "demo_seeds": [s for s in range(seed) if s not in failed],
                "failed_demo_seeds": failed, "demo_files": files}


def training_steps(ws: Path) -> dict:
    """Each trained policy's training steps, from its run's saved config."""
    from sefa_model.policy.checkpoint import resolve_checkpoint

    out = {}
    for name in ("train", "distill", "ddpm"):
        try:
            cfg = json.loads((resolve_checkpoint(ws / name) / "config.json").read_text())
            out[name] = cfg["train_config"]["training"]["max_steps"]
        except (OSError, ValueError, KeyError):
            out[name] = None
    return out


# ----------------------------------------------------------------------------- the report


def binomial_se(successes: list[int]) -> float | None:
    n = len(successes)
    return float(np.std(successes, ddof=1) / np.sqrt(n)) if n > 1 else None


def group_summary(results: dict, tasks: list[str]) -> dict:
    """Per row: success over every episode of these tasks ± its standard error; the student
    minus RK45 paired over (task, seed) ± its standard error; the latency ratio (the mean of
    the student's p50 over the mean of RK45's)."""
    from reflow_rounds import paired

    done = [t for t in tasks if t in results and all(r.slug in results[t]["rows"] for r in ROWS)]
    out = {"tasks": done, "rows": {}}
    if not done:
        return out
    for row in ROWS:
        pooled = [s for t in done for s in results[t]["rows"][row.slug]["per_seed"]]
        out["rows"][row.slug] = (float(np.mean(pooled)), binomial_se(pooled), len(pooled))
    a, b = [], []
    for t in done:  # the same seeds of each task, cut to the shorter
        sa, sb = results[t]["rows"][STUDENT]["per_seed"], results[t]["rows"][TEACHER]["per_seed"]
        n = min(len(sa), len(sb))
        a += sa[:n]
        b += sb[:n]
    out["student_minus_rk45"] = paired(a, b)
    lat = [results[t].get("latency") for t in done]
    if all(lat):
        out["latency_ratio"] = (float(np.mean([x[STUDENT] for x in lat]))
                                / float(np.mean([x[TEACHER] for x in lat])))
    return out


def _cell(p: float, se: float | None) -> str:
    return f"{p:.0%}" + ("" if se is None else f" ± {se:.0%}")


def render(results: dict) -> str:
    from sefa_sim.metaworld import GROUPS, group_of

    names = " | ".join(r.name for r in ROWS)
    lines = ["Per task: success rate ± standard error over the test seeds (from 100000); "
             "p50 latency in ms in brackets.", "",
             f"| task | group | demos | test seeds | training steps (flow / student / ddpm) | {names} |",
             "|---|---|---|---|---|" + "---|" * len(ROWS)]
    plain = []  # tasks whose alignment replaced nothing: their student is no SeFA student
    for task, e in sorted(results.items(), key=lambda kv: (list(GROUPS).index(group_of(kv[0])), kv[0])):
        if not all(r.slug in e.get("rows", {}) for r in ROWS):
            continue
        lat = e.get("latency", {})
        cells = []
        for r in ROWS:
            res = e["rows"][r.slug]
            ms = f" ({lat[r.slug]:.3g})" if r.slug in lat else ""
            mark = " †" if r.slug == STUDENT and res.get("kind", "sefa_one_step") != "sefa_one_step" else ""
            plain += [task] if mark else []
            cells.append(_cell(res["success_rate"], binomial_se(res["per_seed"])) + ms + mark)
        steps = e.get("training_steps", {})
        lines.append(f"| {task} | {group_of(task)} | {e['demos']} | {e['rows'][TEACHER]['n_test']} | "
                     f"{steps.get('train')} / {steps.get('distill')} / {steps.get('ddpm')} | "
                     + " | ".join(cells) + " |")
    if plain:
        lines += ["", f"† {', '.join(plain)}: alignment replaced none of the couplings, so this "
                  "one-step student is plain reflow distillation, not SeFA."]
    lines += ["", "Per group: success over all the group's episodes ± standard error; the one-step "
              "student minus base flow RK45, paired over (task, seed), ± its standard error; "
              "latency student / RK45.", "",
              f"| group | tasks done | {names} | student - RK45 | latency ratio |",
              "|---|---|" + "---|" * len(ROWS) + "---|---|"]
    for group, tasks in [*GROUPS.items(), ("all", [t for g in GROUPS.values() for t in g])]:
        s = group_summary(results, list(tasks))
        if not s["tasks"]:
            continue
        cells = [_cell(p, se) for p, se, _ in (s["rows"][r.slug] for r in ROWS)]
        d, se = s["student_minus_rk45"]
        diff = f"{d:+.1%}" + ("" if se is None else f" ± {se:.1%}")
        ratio = f"{s['latency_ratio']:.3f}" if "latency_ratio" in s else "-"
        lines.append(f"| {group} | {len(s['tasks'])}/{len(tasks)} | " + " | ".join(cells)
                     + f" | {diff} | {ratio} |")
    return "\n".join(lines)


def main() -> None:
    from sefa_sim.metaworld import resolve

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tasks", nargs="*", default=["all"], help="tasks and groups (easy, ..., all)")
    ap.add_argument("--root", type=Path, default=REPO / "runs" / "metaworld-study")
    ap.add_argument("--demos", type=int, default=10, help="successful demonstrations per task")
    ap.add_argument("--n-test", type=int, default=50, help="test seeds per task and row")
    ap.add_argument("--pipeline", default=PIPELINE, help="the SeFA pipeline preset")
    ap.add_argument("--train-preset", default=TRAIN_PRESET, help="the diffusion baseline's")
    ap.add_argument("--report-only", action="store_true")
    ap.add_argument("--dry-run", action="store_true", help="print the commands only")
    args = ap.parse_args()
    tasks = list(dict.fromkeys(t for spec in args.tasks for t in resolve(spec, "--tasks")))
    args.root.mkdir(parents=True, exist_ok=True)
    study = Study(args.root.resolve(), args.demos, args.n_test, args.dry_run, args.pipeline,
                  args.train_preset)
    if not args.report_only:
        for task in tasks:
            study.run_task(task)
    if not args.dry_run:
        print(render(study.results))


if __name__ == "__main__":
    sys.path.insert(0, str(REPO))
    main()
