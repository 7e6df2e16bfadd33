"""How a policy executes its chunks, measured per policy and per execution (docs/results/,
"Execution"): resumable, kept per block of seeds, paired seeds.

    python benchmarks/execution_study.py pusht --root R              # Push-T low-dim, cpu profile
    python benchmarks/execution_study.py pusht_image --root R        # Push-T from its camera
    python benchmarks/execution_study.py metaworld --root R --tasks reach easy
    python benchmarks/execution_study.py report --root R [--json OUT] [--markdown OUT]

Push-T (workspace R/pusht): the `cpu` profile's pipeline (`sefa ingest` of the Diffusion
Policy store, `sefa run pipelines/pusht_lowdim.yaml`, the diffusion baseline `sefa train
pipelines/pusht_lowdim_train.yaml --objective ddpm --out W/ddpm`); image Push-T (R/pusht_image)
the same from its camera (`--key img`, pipelines/pusht_image.yaml and its train config).
Meta-World (R/metaworld/TASK, one workspace per task): benchmarks/metaworld_study.py's
pipeline (10 scripted demonstrations, pipelines/metaworld.yaml, the diffusion baseline). Then, per workspace:

1. `sefa bench latency ROW... --samples 1,4,16,64`: one decision at N samples per row, and what
   each execution costs per control step (the real-time column: a decision's p99 within the
   control period).
2. `sefa choose-execution ROW --env ENV --n-val 50` for each row whose decisions fit the
   control period (validation seeds from 200000; the choice is kept with the policy).
3. `sefa eval ROW --env ENV --execution ...` for every row and execution of its grid, in blocks
   of --block seeds from 100000 (each block a cached evaluation in the workspace and a record in
   R/study.json as soon as it is done; what is left is planned from the seeds recorded, so a
   resumed study may use another --block, e.g. smaller blocks where a block is an hour of
   RK45), the cheapest blocks first (the cost estimated from the latency of step 1), so that
   the table fills in early. On Push-T the headline comes first:
   the student and RK45 are chosen for, then the student under its chosen execution and at 8
   per prediction and RK45 under every execution that fits the control period are evaluated;
   then the other rows' choosers and the rest of the grid. From the camera no RK45 decision
   fits the period on a CPU core (about 380 ms): its bar is its best execution in simulation,
   and the grid is smaller (IMAGE_GRID, 200 and 100 test seeds, the student and RK45 chosen for).

Rows: the one-step student (`distill`), its base flow at RK45 and at Euler-10 (`train`), the
diffusion baseline at DDIM-10 (`ddpm`). Executions: receding horizon replanning every 8, 4, 2
and 1 steps, ACT's ensembling every step, 16 coherent samples every 1, 2 and 4 steps, and
Bidirectional Decoding with 16 samples every step against the base flow at one Euler step;
--skip drops a (row, execution) pair. Every command is run as a child with one torch thread;
--jobs N evaluates N blocks at once (one core each).

Meta-World (50 tasks, 50 test seeds each, many hours on a CPU: run it in pieces, every block
is kept): the chooser runs for the student only, and the grid is smaller where a decision is
slow (META_GRID: the student under every execution and the one chosen for it, RK45 every 8, 4
and 2 steps, Euler-10 every 8 steps and every step, DDIM-10 every 8). Each task is built,
chosen for, and given the blocks the headline needs (the student's chosen execution and 8 per
prediction, RK45 at 8 per prediction) before the next task starts (--jobs N: N tasks at once,
each on one core); then the rest, cheapest first over every task. The report pairs, per group
over (task, seed), the student under its chosen execution with RK45 under its best execution
on those seeds (no RK45 decision fits Meta-World's 12.5 ms control period on a CPU, so its best
in simulation), and prints every row and execution per group.

    python benchmarks/execution_study.py metaworld --root R --tasks all --jobs 2  # start or resume
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import threading
import time
from collections import Counter
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from metaworld_study import Study as MetaWorldBuilder
from reflow_rounds import paired  # mean of a - b over the same seeds, its standard error

REPO = Path(__file__).resolve().parents[1]
PUSHT_STORE = REPO.parent / "shared" / "data" / "pusht_cchi_v7_replay.zarr"
FIRST_TEST_SEED = 100_000
PUSHT_PERIOD_MS = 100.0  # Push-T's control rate: 10 Hz
SIZES = "1,4,16,64"
WEAK = "train@euler-1"


@dataclass(frozen=True)
class Row:
    slug: str
    name: str
    checkpoint: str
    setting: str = ""  # SOLVER-STEPS or SOLVER; "" the checkpoint's own
    multi_step: bool = False

    def solver_args(self) -> list[str]:
        if not self.setting:
            return []
        solver, _, steps = self.setting.partition("-")
        return ["--solver", solver] + (["--steps", steps] if steps else [])

    @property
    def target(self) -> str:
        return self.checkpoint + (f"@{self.setting}" if self.setting else "")


ROWS = (Row("sefa", "SeFA one-step", "distill"),
        Row("base_rk45", "base flow, RK45", "train", "rk45", True),
        Row("base_euler10", "base flow, Euler-10", "train", "euler-10", True),
        Row("ddim10", "diffusion, DDIM-10", "ddpm", "ddim-10", True))
EXECUTIONS = ("receding-8", "receding-4", "receding-2", "receding-1", "ensemble-1",
              "coherent-1x16", "coherent-2x16", "coherent-4x16", "bid-1x16")
# Meta-World's grid per row (50 tasks: where a decision costs 100 ms and more, fewer executions)
META_GRID = {"sefa": EXECUTIONS, "base_rk45": ("receding-8", "receding-4", "receding-2"),
             "base_euler10": ("receding-8", "receding-1"), "ddim10": ("receding-8",)}
# the blocks each Meta-World task gets before the next task starts: the headline's
HEADLINE = (("sefa", "chosen"), ("sefa", "receding-8"), ("base_rk45", "receding-8"))


def execution_args(spec: str) -> list[str]:
    from sefa_model.policy.execution import parse_spec

    s = parse_spec(spec, WEAK)
    out = ["--execution", s.mode]
    if s.replan_every is not None:
        out += ["--replan-every", str(s.replan_every)]
    if s.samples is not None:
        out += ["--samples", str(s.samples)]
    return out + (["--weak", WEAK] if s.mode == "bid" else [])


def target_name(target: str) -> str:
    """A latency record's target as the study names it: `sefa bench latency` run in a workspace
    reports `distill` or, from newer versions, the resolved path `W/distill`; both -> `distill`."""
    return Path(target).name


def spec_of(settings: dict) -> str:
    """An execution record's settings as a spec: receding-4, coherent-1x16, bid-2x16."""
    out = f"{settings['mode']}-{settings['replan_every']}"
    return out + (f"x{settings['samples']}" if (settings.get("samples") or 1) > 1 else "")


def chosen_spec(entry: dict, slug: str) -> str | None:
    """The execution `sefa choose-execution` chose for a row, as a spec (None: not run, or no
    execution fitted its budget). A choice recorded before the chooser kept the default unless
    another execution beat it by 2 standard errors (no `why` in it) is made again by that rule
    from its recorded validation scores."""
    from sefa_pipelines.choose import pick

    choice = entry.get("choices", {}).get(slug) or {}
    label = choice.get("chosen")
    scored = [c for c in choice.get("candidates", []) if c.get("mean_score") is not None]
    if label is not None and "why" not in choice and scored:
        default = max((c for c in scored if c["settings"]["mode"] == "receding"),
                      key=lambda c: c["settings"]["replan_every"])["label"]
        label = pick(scored, default, 2.0)[0]
    row = next((c for c in choice.get("candidates", []) if c.get("label") == label), None)
    return None if row is None else spec_of(row["settings"])


def seed_blocks(done: set[int], n: int, block: int) -> list[tuple[int, int]]:
    """The (first seed, count) blocks of at most `block` consecutive seeds covering the test
    seeds FIRST_TEST_SEED .. +n-1 not in `done`: planned from the seeds recorded, not from block
    names, so a study resumed with another --block neither repeats a seed nor skips one."""
    out, run = [], []
    for seed in range(FIRST_TEST_SEED, FIRST_TEST_SEED + n):
        if seed in done:
            if run:
                out.append((run[0], len(run)))
            run = []
            continue
        run.append(seed)
        if len(run) == block:
            out.append((run[0], block))
            run = []
    return out + ([(run[0], len(run))] if run else [])


class Study:
    def __init__(self, root: Path, dry_run: bool = False, jobs: int = 1):
        self.root, self.dry_run, self.jobs = root, dry_run, jobs
        self.path = root / "study.json"
        self.state = json.loads(self.path.read_text()) if self.path.exists() else {}
        self.lock = threading.Lock()  # blocks run in threads (--jobs) record into one state

    def save(self) -> None:
        from sefa_data import atomic

        atomic.write_json(self.path, self.state)

    def sefa(self, args: list[str], ws: Path | None = None, capture: bool = False,
             check: bool = True, cwd: Path = REPO) -> subprocess.CompletedProcess:
        args = [str(a) for a in args] + (["-w", str(ws)] if ws is not None else [])
        print("$ sefa " + " ".join(args), flush=True)
        env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
        done = subprocess.run([sys.executable, "-m", "sefa_cli.main", *args], cwd=cwd, text=True,
                              env=env, stdout=subprocess.PIPE if capture else None,
                              stderr=subprocess.PIPE if capture else None)
        if check and done.returncode != 0:
            raise SystemExit(f"study: `sefa {' '.join(args)}` failed (exit {done.returncode}): "
                             f"{(done.stderr or '').strip()[-500:]}")
        return done

    # ---- the per-workspace part

    def latency(self, key: str, ws: Path, rows: tuple[Row, ...]) -> dict:
        with self.lock:  # Meta-World's tasks are prepared in threads (--jobs): state under the lock
            entry = self.state.setdefault(key, {})
            if "latency" in entry:
                return entry["latency"]
        targets = [r.target for r in rows] + [WEAK]  # the weaker policy: bid's cost
        out = self.sefa(["bench", "latency", *targets, "--samples", SIZES,
                         "--threads", "1", "--calls", "30", "--warmup", "3",
                         "--max-seconds", "10", "--json"], ws, capture=True, cwd=ws)
        with self.lock:
            entry["latency"] = json.loads(out.stdout)
            self.save()
        return entry["latency"]

    def choose(self, key: str, ws: Path, env: str, rows: tuple[Row, ...], n_val: int) -> None:
        """The chooser for each row (one whose decisions fit no execution is recorded so)."""
        with self.lock:
            entry = self.state.setdefault(key, {}).setdefault("choices", {})
        for row in rows:
            if row.slug in entry:
                continue
            weak = ["--weak", WEAK] if row.slug == "sefa" else []
            out = self.sefa(["choose-execution", row.checkpoint, "--env", env, "--n-val",
                             str(n_val), *row.solver_args(), *weak, "--threads", "1", "--json"],
                            ws, capture=True, check=False)
            with self.lock:
                entry[row.slug] = (json.loads(out.stdout) if out.returncode == 0
                                   else {"chosen": None, "error": out.stderr.strip()})
                self.save()

    def specs(self, key: str, row: Row, grid: dict | None) -> tuple[str, ...]:
        """The executions a row is evaluated under: its grid's (None: every one of EXECUTIONS)
        and, where the chooser ran for it, the one chosen."""
        specs = EXECUTIONS if grid is None else grid.get(row.slug, ())
        chosen = chosen_spec(self.state.get(key, {}), row.slug)
        return tuple(specs) + ((chosen,) if chosen and chosen not in specs else ())

    def blocks(self, key: str, ws: Path, env: str, rows: tuple[Row, ...], seeds: dict,
               block: int, skip: set, latency: dict, steps: int, grid: dict | None = None,
               only: tuple | None = None) -> list[tuple]:
        """Every (cost, row, execution, first seed, n) block not yet done; `only`: the (row,
        execution) pairs to keep, "chosen" standing for the row's chosen execution."""
        from sefa_model.policy.execution import parse_spec

        done = self.state.setdefault(key, {}).setdefault("blocks", {})
        p50 = {(target_name(d["target"]), d["samples"]): d["p50_ms"]
               for d in latency.get("decisions", [])}
        out = []
        for row in rows:
            chosen = chosen_spec(self.state[key], row.slug)
            for spec in self.specs(key, row, grid):
                if (row.slug, spec) in skip or f"{row.slug}:{spec}" in skip:
                    continue
                if only is not None and (row.slug, spec) not in only and not (
                        spec == chosen and (row.slug, "chosen") in only):
                    continue
                s = parse_spec(spec, WEAK).resolved(8)
                ms = p50.get((row.target, s.samples), 100.0) + (
                    p50.get((WEAK, s.samples), 1.0) if s.mode == "bid" else 0.0)
                have = {p["seed"] for name, b in done.items()
                        if name.startswith(f"{row.slug}|{spec}|") for p in b["per_seed"]}
                for first, n in seed_blocks(have, seeds[row.multi_step], block):
                    out.append((n * (steps / s.replan_every) * ms, row, spec, first, n))
        return sorted(out, key=lambda b: b[0])

    def run_block(self, key: str, ws: Path, env: str, row: Row, spec: str, first: int,
                  n: int) -> None:
        started = time.monotonic()
        out = self.sefa(["eval", row.checkpoint, "--env", env, "--n-test", str(n),
                         "--start-seed", str(first), *row.solver_args(), *execution_args(spec),
                         "--threads", "1", "--json"], ws, capture=True)
        result = json.loads(out.stdout)[0]
        log = json.loads((ws / result["eval_log"]).read_text())
        got = sorted(p["seed"] for p in log["per_seed"])
        if got != list(range(first, first + n)):  # the plan counts the seeds recorded
            raise SystemExit(f"execution_study: {ws / result['eval_log']}: per_seed holds "
                             f"{len(got)} seeds, not {first}..{first + n - 1}")
        with self.lock:
            self.record(key, f"{row.slug}|{spec}|{first}", {
            "execution": log["execution_label"], "solver": log["solver"], "nfe": log["nfe"],
            "kind": log["kind"], "eval_log": result["eval_log"],
            "seconds": round(time.monotonic() - started, 1),
            "per_seed": [{"seed": p["seed"], **({"task": p["task"]} if "task" in p else {}),
                          "score": float(p.get("score", p["success"])),
                          "success": bool(p["success"])} for p in log["per_seed"]]})

    def record(self, key: str, name: str, block: dict) -> None:
        self.state[key]["blocks"][name] = block
        self.save()


# ---- Push-T

@dataclass(frozen=True)
class PushT:
    """One Push-T variant of the study: the store's keys ingested, its pipeline (the `cpu`
    profile) and its base flow's train config, the grid per row (None: every row under every
    execution, each row chosen for) and its test seeds (one-step, multi-step)."""
    keys: tuple[str, ...]
    pipeline: str
    train_config: str
    grid: dict | None = None
    seeds: tuple[int, int] = (500, 200)


# From the camera a decision of RK45 costs about 380 ms on a CPU core and the simulator renders
# a frame per executed step (docs/results/pusht_image.md): the multi-step rows get the
# executions their table needs, on fewer seeds, and only the student and RK45 are chosen for.
IMAGE_GRID = {"sefa": EXECUTIONS, "base_rk45": ("receding-8", "receding-4"),
              "base_euler10": ("receding-8", "receding-1"), "ddim10": ("receding-8",)}
PUSHT = {"pusht": PushT(("keypoint", "state"), "pipelines/pusht_lowdim.yaml",
                        "pipelines/pusht_lowdim_train.yaml"),
         "pusht_image": PushT(("img", "state"), "pipelines/pusht_image.yaml",
                              "pipelines/pusht_image_train.yaml", IMAGE_GRID, (200, 100))}


def build_pusht(study: Study, name: str) -> Path:
    """The workspace R/NAME: Push-T ingested with its keys, the pipeline run, and the diffusion
    baseline trained with the base flow's settings (--objective ddpm)."""
    part = PUSHT[name]
    ws = study.root / name
    ws.mkdir(parents=True, exist_ok=True)
    if not (ws / "dataset.zarr").exists():
        study.sefa(["ingest", PUSHT_STORE, "--fps", "10",
                    *[a for k in (*part.keys, "action") for a in ("--key", k)]], ws)
    study.sefa(["run", part.pipeline, "--threads", "1"], ws)
    if not (ws / "ddpm" / "checkpoints" / "latest").exists():
        study.sefa(["train", part.train_config, "--objective", "ddpm", "--out", ws / "ddpm",
                    "--threads", "1"], ws)
    return ws


def pusht(study: Study, args) -> None:
    grid(study, args.part, build_pusht(study, args.part), "pusht", args, steps=300,
         table=PUSHT[args.part].grid)


def grid(study: Study, key: str, ws: Path, env: str, args, steps: int,
         table: dict | None = None) -> None:
    """Push-T's headline first (the student and RK45 chosen for, then the blocks of
    `pusht_headline`), then the other rows' choosers (with a `table`, a grid per row as
    META_GRID: none) and every other block of the grid, cheapest first."""
    study.latency(key, ws, ROWS)
    seeds = {False: args.n_one_step, True: args.n_multi_step}
    skip = set(args.skip or ())
    study.choose(key, ws, env, ROWS[:2], args.n_val)
    headline = pusht_headline(study.state[key], PUSHT_PERIOD_MS)
    run_blocks(study, {key: (ws, env)}, seeds, args.block, skip, headline, steps, table)
    if table is None:
        study.choose(key, ws, env, ROWS, args.n_val)
    run_blocks(study, {key: (ws, env)}, seeds, args.block, skip, None, steps, table)


def pusht_headline(entry: dict, period_ms: float) -> tuple:
    """The (row, execution) pairs Push-T's headline compares: the student under its chosen
    execution and at 8 per prediction, and RK45 under every execution whose decision fits the
    control period (its best real-time score is the bar; where none fits, as from the camera on
    a CPU, RK45 at 8 per prediction in simulation)."""
    rk45 = ROWS[1]
    real = tuple((rk45.slug, spec) for spec in EXECUTIONS
                 if real_time(entry, rk45, spec, period_ms))
    return (("sefa", "chosen"), ("sefa", "receding-8"), *(real or ((rk45.slug, "receding-8"),)))


# ---- Meta-World

def metaworld(study: Study, args) -> None:
    """Every task built, chosen for and given its headline blocks, --jobs tasks at a time (each
    one process at a time, so one core each); then every other block of the grid, cheapest
    first over all the tasks."""
    from sefa_sim.metaworld import resolve

    tasks = list(dict.fromkeys(t for name in args.tasks for t in resolve(name)))
    seeds = {False: args.n_one_step, True: args.n_multi_step}
    skip = set(args.skip or ())

    def prepare(task: str) -> tuple[str, tuple[Path, str]]:
        key = f"metaworld:{task}"
        ws = build_metaworld(study, task)
        study.latency(key, ws, ROWS)
        study.choose(key, ws, key, ROWS[:1], args.n_val)  # the student's execution
        run_blocks(study, {key: (ws, key)}, seeds, args.block, skip, HEADLINE, 500, META_GRID,
                   jobs=1)
        return key, (ws, key)

    with ThreadPoolExecutor(study.jobs) as pool:
        futures = [pool.submit(prepare, task) for task in tasks]
        try:
            built = dict(f.result() for f in futures)
        except BaseException:  # a failed task stops the study: the tasks not started are not
            pool.shutdown(cancel_futures=True)
            raise
    run_blocks(study, built, seeds, args.block, skip, None, 500, META_GRID)


class TaskBuilder(MetaWorldBuilder):
    """benchmarks/metaworld_study.py's builder for one task; its record (the demonstrations
    collected) merged into the shared R/metaworld/results.json under one lock, since tasks are
    built in threads and the builder's own save writes the whole file it read."""
    lock = threading.Lock()

    def __init__(self, root: Path, task: str):
        super().__init__(root, 10, 50, False)
        self.task = task

    def save(self) -> None:
        from sefa_data import atomic

        with self.lock:
            on_disk = json.loads(self.path.read_text()) if self.path.exists() else {}
            on_disk[self.task] = self.results[self.task]
            atomic.write_json(self.path, on_disk)


def build_metaworld(study: Study, task: str) -> Path:
    """benchmarks/metaworld_study.py's workspace of one task (10 scripted demonstrations,
    pipelines/metaworld.yaml, the diffusion baseline), under R/metaworld/TASK."""
    return TaskBuilder(study.root / "metaworld", task).build(task, ("--threads", "1"))


def run_blocks(study: Study, workspaces: dict[str, tuple[Path, str]], seeds: dict, block: int,
               skip: set, only: tuple | None, steps: int, grid: dict | None = None,
               jobs: int | None = None) -> None:
    """The blocks of the given workspaces (key -> its workspace and env), cheapest first over
    all of them, until none is left, `jobs` (default study.jobs) at a time (`only`, `grid`: as
    Study.blocks; `steps`: an episode's). Each block is its own `sefa eval` process on one
    torch thread."""
    jobs = jobs or study.jobs
    running: dict[Future, str] = {}
    with ThreadPoolExecutor(jobs) as pool:
        while True:
            with study.lock:
                todo = sorted(((b, key) for key, (ws, env) in workspaces.items()
                               for b in study.blocks(key, ws, env, ROWS, seeds, block, skip,
                                                     study.state[key]["latency"], steps, grid,
                                                     only)
                               if f"{key}|{b[1].slug}|{b[2]}|{b[3]}" not in running.values()),
                              key=lambda t: t[0][0])
            for (cost, row, spec, first, n), key in todo[:jobs - len(running)]:
                ws, env = workspaces[key]
                print(f"study: {key}: {row.slug} {spec} seeds {first}..{first + n - 1} "
                      f"({len(todo) + len(running)} blocks left, this one about "
                      f"{cost / 1000:.0f} s of policy)", flush=True)
                future = pool.submit(study.run_block, key, ws, env, row, spec, first, n)
                running[future] = f"{key}|{row.slug}|{spec}|{first}"
            if not running:
                return
            done, _ = wait(running, return_when=FIRST_COMPLETED)
            for future in done:
                del running[future]
                future.result()  # a failed block stops the study, as it did one at a time


# ---- the report

def collected(entry: dict) -> dict[tuple[str, str], list[dict]]:
    """(row, execution) -> its per-seed results over every block done, in seed order."""
    out: dict[tuple[str, str], list[dict]] = {}
    for name, block in entry.get("blocks", {}).items():
        row, spec, _ = name.split("|")
        out.setdefault((row, spec), []).extend(block["per_seed"])
    for (row, spec), got in out.items():
        twice = sorted(k for k, c in Counter((p.get("task", ""), p["seed"]) for p in got).items()
                       if c > 1)
        if twice:  # a paired difference would count those episodes twice
            raise SystemExit(f"execution_study: {row} {spec}: seed {twice[0][1]} is recorded in "
                             "more than one block of study.json (remove the extra block)")
    return {k: sorted(v, key=lambda p: (p.get("task", ""), p["seed"])) for k, v in out.items()}


def real_time(entry: dict, row: Row, spec: str, period_ms: float) -> bool | None:
    """A decision of this row at this execution's N (bid: with the weaker policy's) within the
    control period, at FIT_PERCENTILE (p99) of `sefa bench latency`'s decisions, as `sefa
    choose-execution` and `sefa serve` judge it."""
    from sefa_model.eval.latency import FIT_PERCENTILE
    from sefa_model.policy.execution import parse_spec

    s = parse_spec(spec, WEAK).resolved(8)
    worst = {(target_name(d["target"]), d["samples"]): d[FIT_PERCENTILE]
             for d in entry.get("latency", {}).get("decisions", [])}
    own = worst.get((row.target, s.samples))
    if own is None:
        return None
    return own + (worst.get((WEAK, s.samples), 0.0) if s.mode == "bid" else 0.0) <= period_ms


def table(entry: dict, period_ms: float) -> list[dict]:
    """One line per (row, execution) done: its score, seeds, whether it is real time, and its
    difference from the same row at 8 actions per prediction, paired."""
    results = collected(entry)
    lines = []
    for row in ROWS:
        base = results.get((row.slug, "receding-8"))
        extra = sorted({spec for slug, spec in results if slug == row.slug} - set(EXECUTIONS))
        for spec in (*EXECUTIONS, *extra):
            got = results.get((row.slug, spec))
            if not got:
                continue
            line = {"row": row.slug, "name": row.name, "execution": spec,
                    "score": float(np.mean([p["score"] for p in got])),
                    "success": float(np.mean([p["success"] for p in got])), "n": len(got),
                    "real_time": real_time(entry, row, spec, period_ms)}
            if base and spec != "receding-8":
                n = min(len(base), len(got))
                line["minus_receding8"] = paired([p["score"] for p in got[:n]],
                                                 [p["score"] for p in base[:n]])
            lines.append(line)
    return lines


def scores(results: dict, slug: str, spec: str | None, n: int) -> dict | None:
    """{(task, seed): score} of a row under an execution, when all n seeds are done."""
    got = results.get((slug, spec)) if spec else None
    if not got or len(got) < n:
        return None
    return {(p.get("task", ""), p["seed"]): p["score"] for p in got[:n]}


def best_spec(results: dict, slug: str, n: int) -> str | None:
    """The execution with the highest mean score over the row's complete ones (on the test
    seeds: a teacher's best in hindsight, which favours the teacher)."""
    done = {spec: v for (s, spec) in results
            if s == slug and (v := scores(results, slug, spec, n)) is not None}
    return best_of(done) if done else None


def pusht_summary(entry: dict, n: int) -> dict:
    """Push-T's headline over the first n test seeds, paired: the student under its chosen
    execution minus RK45 under its best real-time execution (the best on these seeds, in
    hindsight: it favours the teacher; where no RK45 decision fits the control period, its best
    in simulation, and `rk45_real_time` is False) and under the one chosen for it (the table
    has the student against its own 8 per prediction). A row not done on n seeds is left out."""
    results = collected(entry)
    rk45 = ROWS[1]
    student_spec = chosen_spec(entry, "sefa")
    done = {spec: v for (slug, spec) in results if slug == rk45.slug
            and (v := scores(results, slug, spec, n)) is not None}
    real = {spec: v for spec, v in done.items()
            if real_time(entry, rk45, spec, PUSHT_PERIOD_MS)}
    judged = [j for spec in EXECUTIONS
              if (j := real_time(entry, rk45, spec, PUSHT_PERIOD_MS)) is not None]
    fits = any(judged) if judged else None  # None: RK45's latency not recorded
    bar = real if fits else done
    out = {"student": student_spec, "n": n, "rk45_real_time": fits}
    student = scores(results, "sefa", student_spec, n)
    if student is None:
        return out
    if bar:
        out["spec_best"] = max(bar, key=lambda spec: np.mean(list(bar[spec].values())))
        teacher = bar[out["spec_best"]]
        out["minus_best"] = paired([student[k] for k in sorted(student)],
                                   [teacher[k] for k in sorted(student)])
    chosen = chosen_spec(entry, rk45.slug)
    if chosen in real:
        out["spec_rk45_chosen"] = chosen
        out["minus_rk45_chosen"] = paired([student[k] for k in sorted(student)],
                                          [real[chosen][k] for k in sorted(student)])
    return out


def groups_and_all() -> list[tuple[str, tuple[str, ...]]]:
    """Meta-World's difficulty groups and their tasks, then `all` of them."""
    from sefa_sim.metaworld import GROUPS

    return [*GROUPS.items(), ("all", tuple(t for g in GROUPS.values() for t in g))]


def cross_picked(per_spec: dict[str, dict]) -> dict:
    """{seed key: score} of a row under its best execution without the bonus of picking and
    scoring on the same seeds: the seeds in two halves, each scored under the execution best on
    the other half (a tie goes to the execution listed first)."""
    keys = sorted(next(iter(per_spec.values())))
    halves = (keys[:len(keys) // 2], keys[len(keys) // 2:])
    out = {}
    for mine, other in (halves, halves[::-1]):
        pick = max(per_spec, key=lambda sp: np.mean([per_spec[sp][k] for k in other]))
        out.update({k: per_spec[pick][k] for k in mine})
    return out


def task_headline(entry: dict, n: int) -> dict | None:
    """A Meta-World task's headline on n seeds, {(task, seed): score} each: the student under
    its chosen execution and at 8 per prediction, RK45 under its best (in hindsight, and picked
    on the other half of the seeds: `cross_picked`) and at 8 per prediction; None until all
    four are done."""
    results = collected(entry)
    spec, best = chosen_spec(entry, "sefa"), best_spec(results, "base_rk45", n)
    h = {"chosen": spec, "rk45_spec": best,
         "student": scores(results, "sefa", spec, n),
         "s8": scores(results, "sefa", "receding-8", n),
         "teacher": scores(results, "base_rk45", best, n),
         "t8": scores(results, "base_rk45", "receding-8", n)}
    if any(h[k] is None for k in ("student", "s8", "teacher", "t8")):
        return None
    rk45 = {sp: v for sp in META_GRID["base_rk45"]
            if (v := scores(results, "base_rk45", sp, n)) is not None}
    return h | {"teacher_cross": cross_picked(rk45)}


def group_summary(state: dict, n: int = 50) -> list[dict]:
    """Meta-World per group: the student under its chosen execution minus RK45 under its best
    (and both at 8 per prediction), paired over (task, seed) on the tasks where both are done;
    how many of the group's tasks that is."""
    lines = []
    for group, tasks in groups_and_all():
        pairs = {"chosen": ([], []), "receding-8": ([], []), "cross": ([], [])}
        counted = []
        for task in tasks:
            h = task_headline(state.get(f"metaworld:{task}", {}), n)
            if h is None:
                continue
            counted.append(task)
            for name, (a, b) in (("chosen", (h["student"], h["teacher"])),
                                 ("receding-8", (h["s8"], h["t8"])),
                                 ("cross", (h["student"], h["teacher_cross"]))):
                pairs[name][0].extend(a[k] for k in sorted(a))
                pairs[name][1].extend(b[k] for k in sorted(a))
        line = {"group": group, "tasks": len(counted), "of": len(tasks)}
        if counted:
            a, b = pairs["chosen"]
            line.update(student_chosen=float(np.mean(a)), rk45_best=float(np.mean(b)),
                        minus=paired(a, b), minus_receding8=paired(*pairs["receding-8"]),
                        rk45_cross=float(np.mean(pairs["cross"][1])),
                        minus_cross=paired(*pairs["cross"]))
        lines.append(line)
    return lines


def choice_table(state: dict, n: int = 50) -> list[dict]:
    """Meta-World per group, what is the policy and what is the choice of its execution: the
    student under the execution chosen on validation seeds, under its grid's best picked on the
    other half of the test seeds and in hindsight, each against RK45 picked the same way (its
    three executions), paired over (task, seed); on the tasks where the student's whole grid
    and RK45's are done."""
    lines = []
    for group, tasks in groups_and_all():
        cols: dict[str, list[float]] = {k: [] for k in (
            "student_chosen", "student_cross", "student_hindsight", "rk45_cross",
            "rk45_hindsight")}
        counted = 0
        for task in tasks:
            entry = state.get(f"metaworld:{task}", {})
            results = collected(entry)
            chosen = scores(results, "sefa", chosen_spec(entry, "sefa"), n)
            grids = [{sp: scores(results, slug, sp, n) for sp in META_GRID[slug]}
                     for slug in ("sefa", "base_rk45")]
            if chosen is None or any(v is None for g in grids for v in g.values()):
                continue
            counted += 1
            keys = sorted(chosen)
            for name, got in (("student_chosen", chosen),
                              ("student_cross", cross_picked(grids[0])),
                              ("student_hindsight", grids[0][best_of(grids[0])]),
                              ("rk45_cross", cross_picked(grids[1])),
                              ("rk45_hindsight", grids[1][best_of(grids[1])])):
                cols[name].extend(got[k] for k in keys)
        line = {"group": group, "tasks": counted, "of": len(tasks)}
        if counted:
            line |= {k: float(np.mean(v)) for k, v in cols.items()} | {
                "chosen_minus_rk45_cross": paired(cols["student_chosen"], cols["rk45_cross"]),
                "cross_minus_rk45_cross": paired(cols["student_cross"], cols["rk45_cross"]),
                "hindsight_minus_rk45_hindsight": paired(cols["student_hindsight"],
                                                         cols["rk45_hindsight"])}
        lines.append(line)
    return lines


def best_of(per_spec: dict[str, dict]) -> str:
    """The execution with the highest mean score (a tie to the one listed first)."""
    return max(per_spec, key=lambda sp: np.mean(list(per_spec[sp].values())))


def group_table(state: dict, n: int = 50) -> list[dict]:
    """Meta-World's full table per group: each row under each execution of its grid (the
    student also under the one chosen per task), its mean score over the group's tasks where
    all n seeds are done, and its difference from the same row at 8 per prediction, paired over
    (task, seed) on the tasks where both are done."""
    lines = []
    for group, tasks in groups_and_all():
        entries = {t: state[f"metaworld:{t}"] for t in tasks if f"metaworld:{t}" in state}
        results = {t: collected(e) for t, e in entries.items()}
        for row in ROWS:
            specs = META_GRID[row.slug] + (("chosen",) if row.slug == "sefa" else ())
            for spec in specs:
                got, base = {}, {}
                for t, res in results.items():
                    own = chosen_spec(entries[t], row.slug) if spec == "chosen" else spec
                    if (v := scores(res, row.slug, own, n)) is not None:
                        got[t] = v
                        if (b := scores(res, row.slug, "receding-8", n)) is not None:
                            base[t] = b
                if not got:
                    continue
                line = {"group": group, "row": row.slug, "name": row.name, "execution": spec,
                        "tasks": len(got), "of": len(tasks),
                        "score": float(np.mean([x for v in got.values() for x in v.values()]))}
                if spec != "receding-8" and base:
                    keys = [(t, k) for t in sorted(base) for k in sorted(got[t])]
                    line["minus_receding8"] = paired([got[t][k] for t, k in keys],
                                                     [base[t][k] for t, k in keys])
                    line["paired_tasks"] = len(base)
                lines.append(line)
    return lines


def task_table(state: dict, n: int = 50) -> list[dict]:
    """Meta-World task by task, in group order: the execution chosen for the student, its
    score under it and at 8 per prediction, RK45's best execution and score, and the student
    under its chosen execution minus RK45 under its best, paired over the task's seeds. A task
    whose headline is not done on n seeds (`task_headline`) is left out."""
    from sefa_sim.metaworld import GROUPS

    lines = []
    for group, tasks in GROUPS.items():
        for task in tasks:
            h = task_headline(state.get(f"metaworld:{task}", {}), n)
            if h is None:
                continue
            student, teacher = h["student"], h["teacher"]
            keys = sorted(student)
            lines.append({"task": task, "group": group, "chosen": h["chosen"],
                          "student_chosen": float(np.mean([student[k] for k in keys])),
                          "student_receding8": float(np.mean(list(h["s8"].values()))),
                          "rk45_spec": h["rk45_spec"],
                          "rk45_best": float(np.mean([teacher[k] for k in keys])),
                          "minus": paired([student[k] for k in keys],
                                          [teacher[k] for k in keys])})
    return lines


def spec_words(spec: str) -> str:
    """An execution as the docs' tables name it."""
    if spec == "chosen":
        return "chosen per task"
    mode, _, rest = spec.partition("-")
    k, _, n = rest.partition("x")
    every = "every step" if k == "1" else f"every {k} steps"
    return {"receding": "8 per prediction" if k == "8" else f"receding, {every}",
            "ensemble": f"ACT's ensembling, {every}", "coherent": f"{n} coherent, {every}",
            "bid": f"BID of {n}, {every}"}[mode]


def _cell(line: dict | None) -> str:
    if line is None:
        return ""
    text = f"{line['score']:.1%}".replace("%", " %")
    if line.get("minus_receding8"):
        text += f" ({pts(line['minus_receding8'])})"
    return text + ("" if line["tasks"] == line["of"] else f" [{line['tasks']} of {line['of']}]")


def pts(d: tuple[float, float | None]) -> str:
    """A paired difference of success rates in points: +1.2 ± 0.4."""
    return f"{100 * d[0]:+.1f} ± {100 * (d[1] or 0):.1f}"


def choice_markdown(state: dict, n: int = 50) -> list[str]:
    """`choice_table` for the docs (after a blank line), once some task's whole grid is done."""
    choice = [g for g in choice_table(state, n) if g["tasks"]]
    if not choice:
        return []
    out = ["", "| group | tasks | SeFA one-step, chosen | picked on the other half | in hindsight "
           "| RK45, picked on the other half | in hindsight | chosen - RK45 picked on the other "
           "half | both picked on the other half | both in hindsight |",
           "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for g in choice:
        out.append(f"| {g['group'].replace('_', ' ')} | {g['tasks']} of {g['of']} | "
                   + " | ".join(f"{g[k]:.1%}".replace("%", " %") for k in (
                       "student_chosen", "student_cross", "student_hindsight", "rk45_cross",
                       "rk45_hindsight"))
                   + " | " + " | ".join(pts(g[k]) for k in (
                       "chosen_minus_rk45_cross", "cross_minus_rk45_cross",
                       "hindsight_minus_rk45_hindsight")) + " |")
    return out


def markdown(state: dict, n: int = 50) -> str:
    """Meta-World's tables for the docs: per group, the student under its chosen execution
    against RK45's best (and both at 8 per prediction), paired over (task, seed), in points;
    every row and execution per group (mean success, and against the same row at 8 per
    prediction in points; [k of m] where not every task is done); the policy against the
    choice of its execution (`choice_table`); which execution was chosen for the student on how
    many tasks; and task by task, the headline's pair."""
    groups = [g for g, _ in groups_and_all()]
    names = " | ".join(g.replace("_", " ") for g in groups)
    out = ["| group | tasks | SeFA one-step, chosen | RK45, its best | student - RK45 (points) "
           "| both at 8 per prediction | RK45, picked on the other half of the seeds | student "
           "- it (points) |", "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for g in group_summary(state, n):
        if "minus" not in g:
            out.append(f"| {g['group'].replace('_', ' ')} | 0 of {g['of']} | | | | | | |")
            continue
        out.append(f"| {g['group'].replace('_', ' ')} | {g['tasks']} of {g['of']} | "
                   f"{g['student_chosen']:.1%} | {g['rk45_best']:.1%} | {pts(g['minus'])} | "
                   f"{pts(g['minus_receding8'])} | {g['rk45_cross']:.1%} | "
                   f"{pts(g['minus_cross'])} |".replace("%", " %"))
    lines = {(g["group"], g["row"], g["execution"]): g for g in group_table(state, n)}
    out += ["", f"| policy | execution | {names} |",
            "|---|---|" + "---:|" * len(groups)]
    for row in ROWS:
        for spec in META_GRID[row.slug] + (("chosen",) if row.slug == "sefa" else ()):
            cells = [_cell(lines.get((g, row.slug, spec))) for g in groups]
            if any(cells):
                out.append(f"| {row.name} | {spec_words(spec)} | " + " | ".join(cells) + " |")
    counts: dict[str, dict[str, int]] = {}
    for group, tasks in groups_and_all():
        for t in tasks:
            spec = chosen_spec(state.get(f"metaworld:{t}", {}), "sefa")
            if spec is not None:
                counts.setdefault(spec, dict.fromkeys(groups, 0))[group] += 1
    out += choice_markdown(state, n)
    out += ["", f"| chosen for the student | {names} |",
            "|---|" + "---:|" * len(groups)]
    for spec in sorted(counts, key=lambda sp: -counts[sp]["all"]):
        out.append(f"| {spec_words(spec)} | " + " | ".join(str(counts[spec][g]) for g in groups)
                   + " |")
    out += ["", "| task | group | chosen for the student | SeFA one-step, chosen "
            "| at 8 per prediction | RK45, its best | student - RK45 (points) |",
            "|---|---|---|---:|---:|---:|---:|"]
    for t in task_table(state, n):
        m, se = t["minus"]
        out.append(f"| {t['task']} | {t['group'].replace('_', ' ')} | {spec_words(t['chosen'])} | "
                   f"{t['student_chosen']:.0%} | {t['student_receding8']:.0%} | "
                   f"{t['rk45_best']:.0%} ({spec_words(t['rk45_spec'])}) | "
                   f"{100 * m:+.0f} ± {100 * (se or 0):.0f} |".replace("%", " %"))
    return "\n".join(out) + "\n"


def report(study: Study, args) -> None:
    out = {}
    for key, entry in study.state.items():
        period = PUSHT_PERIOD_MS if key in PUSHT else 12.5  # Meta-World at 80 Hz
        out[key] = {"table": table(entry, period),
                    "chosen": {k: chosen_spec(entry, k) for k in entry.get("choices", {})}}
        print(f"== {key} (control period {period:g} ms); chosen: {out[key]['chosen']}")
        if key in PUSHT:
            out[key]["headline"] = line = pusht_summary(
                entry, args.n_multi_step or PUSHT[key].seeds[1])
            best = {True: "RK45 under its best real-time execution",
                    False: "RK45 under its best execution in simulation (no RK45 decision fits "
                           "the control period)",
                    None: "RK45 under its best execution in simulation (RK45's latency is not "
                          "recorded)"}[line["rk45_real_time"]]
            for name, what in (("minus_best", best),
                               ("minus_rk45_chosen", "RK45 under the execution chosen for it")):
                if line.get(name):
                    m, se = line[name]
                    print(f"the student under {line['student']} minus {what} "
                          f"({line.get(name.replace('minus', 'spec'))}): {m:+.3f} ± {se or 0:.3f}, "
                          f"paired over {line['n']} seeds")
        for line in out[key]["table"]:
            diff = line.get("minus_receding8")
            d = "" if diff is None else f"  {diff[0]:+.3f} ± {diff[1] or 0:.3f} vs receding-8"
            rt = {True: "real time", False: "not real time", None: "?"}[line["real_time"]]
            print(f"{line['name']:22s} {line['execution']:14s} {line['score']:.3f} "
                  f"(success {line['success']:.0%}, {line['n']} seeds, {rt}){d}")
    if any(k.startswith("metaworld:") for k in study.state):
        out["metaworld_table"] = group_table(study.state)
        print("== Meta-World per group: each row and execution, mean success over the tasks done "
              "(and against the same row at 8 per prediction, paired over (task, seed))")
        for g in out["metaworld_table"]:
            diff = g.get("minus_receding8")
            d = "" if diff is None else (f"  {pts(diff)} "
                                         f"points vs receding-8 ({g['paired_tasks']} tasks)")
            print(f"{g['group']:10s} {g['name']:22s} {g['execution']:14s} {g['score']:6.1%} "
                  f"({g['tasks']} of {g['of']} tasks){d}")
        out["metaworld_groups"] = group_summary(study.state)
        print("== Meta-World per group: the student under its chosen execution - RK45 under its "
              "best, paired over (task, seed) (and both at 8 per prediction)")
        for g in out["metaworld_groups"]:
            if "minus" not in g:
                print(f"{g['group']:10s} 0 of {g['of']} tasks done")
                continue
            print(f"{g['group']:10s} {g['tasks']} of {g['of']} tasks: student {g['student_chosen']:.1%}"
                  f", RK45 best {g['rk45_best']:.1%}, difference {pts(g['minus'])} points (at 8 "
                  f"per prediction {pts(g['minus_receding8'])}; RK45 picked on the other half of "
                  f"the seeds {g['rk45_cross']:.1%}, difference {pts(g['minus_cross'])})")
        out["metaworld_choice"] = choice_table(study.state)
        if table_lines := choice_markdown(study.state):
            print("== Meta-World per group: the policy and the choice of its execution (the tasks "
                  "whose grids are done)", *table_lines[1:], sep="\n")
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))
    if args.markdown:
        args.markdown.write_text(markdown(study.state))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("part", choices=(*PUSHT, "metaworld", "report"))
    ap.add_argument("--root", type=Path, default=REPO / "runs" / "execution-study")
    ap.add_argument("--tasks", nargs="*", default=["reach"], help="Meta-World tasks or groups")
    ap.add_argument("--n-one-step", type=int, help="test seeds of the one-step student "
                    "(default: Push-T 500, from its camera 200, Meta-World 50 per task)")
    ap.add_argument("--n-multi-step", type=int, help="test seeds of the multi-step rows "
                    "(default: Push-T 200, from its camera 100, Meta-World 50 per task)")
    ap.add_argument("--n-val", type=int, default=50)
    ap.add_argument("--block", type=int, default=50)
    ap.add_argument("--jobs", type=int, default=1, help="blocks evaluated at once, each a "
                    "process on one torch thread (at most the machine's free cores)")
    ap.add_argument("--skip", nargs="*", help="ROW:EXECUTION pairs not to run (base_rk45:receding-1)")
    ap.add_argument("--json", type=Path, help="report: write the tables here")
    ap.add_argument("--markdown", type=Path, help="report: Meta-World's tables for the docs")
    args = ap.parse_args()
    if args.part != "report":  # the report takes each part's own unless told
        one_step, multi_step = PUSHT[args.part].seeds if args.part in PUSHT else (50, 50)
        args.n_one_step = args.n_one_step or one_step
        args.n_multi_step = args.n_multi_step or multi_step
    args.root.mkdir(parents=True, exist_ok=True)
    if args.jobs < 1:
        raise SystemExit(f"study: --jobs must be 1 or more, not {args.jobs}")
    study = Study(args.root.resolve(), jobs=args.jobs)
    {**dict.fromkeys(PUSHT, pusht), "metaworld": metaworld, "report": report}[args.part](study, args)


if __name__ == "__main__":
    main()
