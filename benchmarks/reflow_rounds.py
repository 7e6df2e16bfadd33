"""The reflow-rounds study on Push-T low-dim (issue 11): does error accumulate as reflow repeats,
and does selective alignment stop it?

For rounds k = 1..R, three variants, each distilled to one step:

    unaligned        couplings of round k, distilled as they are      (sefa distill --no-align)
    aligned_final    round k's couplings aligned only before distillation        (sefa distill)
    aligned_rounds   every round's couplings aligned before the next round trains on them, and
                     before distillation              (sefa reflow --align-rounds; sefa distill)

Round 1 of aligned_rounds is aligned_final's round 1 (nothing trains before it). Per row: score
and success over the same test seeds, with the standard error of the difference to the base
flow (RK45) and to the same round's unaligned row, paired over seeds; how straight the round's
flow is (the RK45 network evaluations per solve of its couplings); and how far its couplings
drift from the expert chunks (mean distance, fraction within eps), read from the couplings.

    python benchmarks/reflow_rounds.py -w runs/rounds              # the defaults below
    python benchmarks/reflow_rounds.py -w W --rounds 2 --windows 16 --samples 2 \\
        --train-steps 20 --flow-steps 20 --student-steps 20 --n-test 1 --max-steps 20   # a smoke run

The base flow is the `cpu` profile's (pipelines/pusht_lowdim_train.yaml: step 30,000 of a
50,000-step schedule), rolled out with RK45 on --base-n-test seeds (paired with the students over
those seeds); --train-steps N trains N steps on its own schedule instead, and --base-from CKPT
continues a kept checkpoint of the preset's very run (the budget curve's step_30000) into the
workspace's train stage instead of training it again. At the end, two sweeps on round 1:
eps (--eps-sweep, the same couplings aligned at each eps) and K (--k-sweep, noises per window,
each distilled unaligned and aligned at --eps).

Every step is a `sefa` command in the workspace W (printed as it runs, cached by the stage
runner); students are copied to W/rows/<row> and their rollouts cached there, so an interrupted
study continues. The result goes to W/rounds.json and, as a markdown table, to stdout.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import yaml

from sefa_data import atomic
from sefa_data.bench.throughput import DEFAULT_DATA_DIR

REPO = Path(__file__).resolve().parents[1]
PUSHT_FILE = "pusht_cchi_v7_replay.zarr"
VARIANTS = ("unaligned", "aligned_final", "aligned_rounds")


def sefa(ws: Path, *args: str, capture: bool = False) -> str:
    print("$ sefa " + " ".join(args), flush=True)
    done = subprocess.run([sys.executable, "-m", "sefa_cli.main", *args, "-w", str(ws)], cwd=REPO,
                          text=True, stdout=subprocess.PIPE if capture else None)
    if done.returncode != 0:
        raise SystemExit(f"reflow_rounds: `sefa {' '.join(args)}` failed (exit {done.returncode})")
    return done.stdout or ""


def train_overrides(args: argparse.Namespace) -> list[str]:
    steps = ([] if args.train_steps is None else
             [f"training.max_steps={args.train_steps}", "training.lr_decay_steps=null"])
    return steps + val_overrides(args)


def val_overrides(args: argparse.Namespace) -> list[str]:
    """--val-windows for every training of the study (the study reads no validation number: a
    tiny study spends most of its time sampling the preset's 256 windows with RK45)."""
    return [] if args.val_windows is None else [f"training.val_sample_windows={args.val_windows}"]


def seed_base(ws: Path, ckpt: Path, pipeline: Path | None = None) -> None:
    """Put a kept checkpoint of the preset's own run where an interrupted train stage keeps its
    last checkpoint, recording the stage's config in it: `sefa train` then continues it (at
    max_steps: nothing left to train) and publishes it as the train stage. Refused unless the
    checkpoint's run had the same config apart from its length and cadence, and the same cosine
    schedule (so its weights are what the stage would train: tests/sefa_model_tests/test_sefa_stages.py)."""
    from sefa_pipelines.runner import Workspace, run_id
    from sefa_pipelines.stages import base_train_config, load_pipeline, stages
    from sefa_data.config_io import from_dict
    from sefa_data.store.zarr_store import EpisodeStore
    from sefa_model.policy.checkpoint import write_checksums
    from sefa_model.config import TrainConfig, config_to_dict
    from sefa_model.policy.model import resolve_shapes

    if not (ckpt / "config.json").is_file():
        raise SystemExit(f"--base-from {ckpt}: not a checkpoint (no config.json)")
    workspace = Workspace(ws)
    pipe = load_pipeline(ws, pipeline)  # the workspace's sefa.yaml, or the pipeline it will run
    stage = stages(ws, pipe)[0]
    if workspace.status(stage).state == "cached":
        return
    # as training records it: shapes resolved from the store
    cfg = resolve_shapes(base_train_config(ws, pipe), EpisodeStore.open(ws / "dataset.zarr"))
    want = config_to_dict(cfg)
    recorded = json.loads((ckpt / "config.json").read_text())
    have = recorded["train_config"]
    length = lambda t: t.get("lr_decay_steps") or t["max_steps"]
    if length(have["training"]) != length(want["training"]):
        raise SystemExit(f"--base-from {ckpt}: its cosine schedule is {length(have['training'])} "
                         f"steps long, the preset's {length(want['training'])}")
    cadence = {"max_steps", "lr_decay_steps", "val_every", "checkpoint_every", "keep_every",
               "device", "num_workers", "wandb"}
    # the recorded config read as today's (fields added since take their defaults)
    have_cfg = config_to_dict(from_dict(TrainConfig, have, source=str(ckpt / "config.json")))
    differ = [key for key, a, b in _leaves(have_cfg, want) if key.split(".")[-1] not in cadence]
    if differ:
        raise SystemExit(f"--base-from {ckpt}: not a checkpoint of the preset's run "
                         f"(differs in {', '.join(differ)})")
    partial = workspace.partial_dir(stage.artifact, run_id(stage, workspace.input_fingerprints(stage)))
    shutil.rmtree(partial, ignore_errors=True)
    shutil.copytree(ckpt, partial / "checkpoints" / "latest")
    for name in ("normalizer.json", "normalizer.safetensors"):
        shutil.copy2(ckpt / name, partial / name)
    atomic.write_json(partial / "checkpoints" / "latest" / "config.json",
                      {**recorded, "train_config": want})
    write_checksums(partial / "checkpoints" / "latest")  # the config is rewritten on purpose
    print(f"base flow: continuing {ckpt} as the train stage", flush=True)


def _leaves(a, b, key: str = ""):
    """(dotted key, a's value, b's value) for every leaf where two nested dicts differ."""
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(set(a) | set(b)):
            yield from _leaves(a.get(k), b.get(k), f"{key}.{k}" if key else k)
    elif a != b:
        yield key, a, b


def write_pipeline(ws: Path, args: argparse.Namespace) -> None:
    """The `cpu` profile's pipeline with the study's sizes (a changed size reruns what it touches)."""
    pipe = yaml.safe_load((REPO / "pipelines" / "pusht_lowdim.yaml").read_text())
    pipe["train_config"] = str(REPO / "pipelines" / pipe["train_config"])
    pipe["train"] = train_overrides(args)
    every = [f"training.val_every={args.flow_steps}", f"training.checkpoint_every={args.flow_steps}"]
    # a batch is drawn from the couplings: never more than there are (a tiny study's few)
    couplings = args.windows * args.samples
    cap = [f"training.batch_size={couplings}"] if couplings < 256 else []  # the preset's 256
    pipe["reflow"].update(samples_per_window=args.samples, max_windows=args.windows,
                          train_overrides=[f"training.max_steps={args.flow_steps}"] + every + cap
                          + val_overrides(args))
    pipe["align"]["eps"] = args.eps
    pipe["distill"]["train_overrides"] = [
        f"training.max_steps={args.student_steps}", f"training.val_every={args.student_steps}",
        f"training.checkpoint_every={args.student_steps}"] + cap + val_overrides(args)
    path = ws / "sefa.yaml"
    text = yaml.safe_dump(pipe, sort_keys=False)
    if not path.exists() or path.read_text() != text:
        atomic.write_text(path, text)


def couplings_attrs(ws: Path, round_: int) -> dict:
    import zarr

    attrs = dict(zarr.open_group(str(ws / f"reflow/iter_{round_}/couplings.zarr"), mode="r").attrs)
    return {"nfe_per_solve": attrs["nfe_per_solve"], "evals_per_coupling": attrs["evals_per_coupling"],
            "drift": attrs["expert_drift"]}


def rollout(ws: Path, ckpt: str, args: argparse.Namespace, solver: list[str],
            n_test: int | None = None) -> dict:
    n_test = n_test or args.n_test
    out = ws / ckpt / f"eval_pusht_{'_'.join(solver) or 'own'}_{n_test}_{args.max_steps}"
    if not (out / "eval_log.json").exists():
        sefa(ws, "eval", str(ws / ckpt), "--env", "pusht", "--n-test", str(n_test),
             "--max-steps", str(args.max_steps), "--out", str(out), *solver, "--json", capture=True)
    log = json.loads((out / "eval_log.json").read_text())
    return {"score": log["test/mean_score"], "success": log["test/success_rate"],
            "per_seed": [r["score"] for r in log["per_seed"]]}


def paired(a: list[float], b: list[float]) -> tuple[float, float | None]:
    """Mean of a - b over the same seeds and its standard error (the seeds' difficulty cancels).
    Both start at the same seed; the longer one is cut to the shorter's seeds."""
    n = min(len(a), len(b))
    diff = np.asarray(a[:n]) - np.asarray(b[:n])
    se = float(diff.std(ddof=1) / np.sqrt(len(diff))) if len(diff) > 1 else None
    return float(diff.mean()), se


def build_rows(ws: Path, args: argparse.Namespace) -> list[dict]:
    rows = []
    for variant in VARIANTS:
        for k in range(1, args.rounds + 1):
            slug = f"{variant}_r{k}"
            if variant == "aligned_rounds" and k == 1:
                slug = "aligned_final_r1"  # the same student: nothing trains before round 1
            else:
                make_row(ws, slug, k, args.samples, variant == "aligned_rounds",
                         None if variant == "unaligned" else args.eps)
            rows.append({"variant": variant, "round": k, "slug": slug, **row_stats(ws, slug)})
    return rows


def make_row(ws: Path, slug: str, round_: int, samples: int, align_rounds: bool,
             eps: float | None) -> None:
    """Reflow to `round_` with K = `samples`, distil (aligned at `eps` unless None) and keep the
    student in W/rows/<slug> with its couplings' statistics; nothing if it is kept already."""
    if (ws / "rows" / slug / "checkpoints" / "latest").exists():
        return
    started = time.perf_counter()
    sefa(ws, "reflow", "--iters", str(round_), "--samples", str(samples),
         "--align-rounds" if align_rounds else "--no-align-rounds")
    if eps is None:
        sefa(ws, "distill", "--no-align")
    else:
        sefa(ws, "align", "--eps", f"{eps:g}")
        sefa(ws, "distill", "--align")
    shutil.rmtree(ws / "rows" / slug, ignore_errors=True)
    shutil.copytree(ws / "distill", ws / "rows" / slug)
    atomic.write_json(ws / "rows" / slug / "coupling_stats.json",
                      {**couplings_attrs(ws, round_), "seconds": time.perf_counter() - started})


def row_stats(ws: Path, slug: str) -> dict:
    return json.loads((ws / "rows" / slug / "coupling_stats.json").read_text())


def build_sweeps(ws: Path, args: argparse.Namespace) -> list[dict]:
    """Round 1 only. eps: round 1's couplings aligned at each eps, then distilled. K: round 1
    regenerated with K noises per window, distilled unaligned and aligned at --eps."""
    rows = []
    for eps in args.eps_sweep:
        rows.append({"sweep": "eps", "eps": eps, "samples": args.samples, "aligned": True,
                     "slug": f"eps{eps:g}_r1"})
    for k in args.k_sweep:
        for aligned in (False, True):
            rows.append({"sweep": "K", "eps": args.eps if aligned else None, "samples": k,
                         "aligned": aligned, "slug": f"K{k}_{'aligned' if aligned else 'unaligned'}_r1"})
    for row in rows:
        make_row(ws, row["slug"], 1, row["samples"], False, row["eps"])
        row.update(row_stats(ws, row["slug"]))
    if args.k_sweep:  # leave the workspace at the study's own K
        sefa(ws, "reflow", "--iters", "1", "--samples", str(args.samples), "--no-align-rounds")
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("-w", "--workspace", type=Path, default=None, help="required unless --plot-from")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--windows", type=int, default=1000, help="training windows reflowed per round")
    ap.add_argument("--samples", type=int, default=5, help="noises per window (K)")
    ap.add_argument("--train-steps", type=int, default=None,
                    help="base flow: N steps on its own schedule (default: the preset's)")
    ap.add_argument("--base-from", type=Path, default=None, metavar="CKPT",
                    help="a kept checkpoint of the preset's own run, continued as the base flow")
    ap.add_argument("--base-n-test", type=int, default=200, help="seeds for the RK45 base flow")
    ap.add_argument("--eps-sweep", type=float, nargs="*", default=[],
                    help="round 1's couplings aligned at each of these eps")
    ap.add_argument("--k-sweep", type=int, nargs="*", default=[],
                    help="round 1 with each of these K, unaligned and aligned at --eps")
    ap.add_argument("--val-windows", type=int, default=None,
                    help="windows sampled for each training's validation MSE (default: the "
                         "preset's)")
    ap.add_argument("--flow-steps", type=int, default=1000, help="each reflowed flow (round >= 2)")
    ap.add_argument("--student-steps", type=int, default=1000, help="each one-step student")
    ap.add_argument("--eps", type=float, default=0.05)
    ap.add_argument("--n-test", type=int, default=500)
    ap.add_argument("--max-steps", type=int, default=300)
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA_DIR,
                    help=f"the folder holding {PUSHT_FILE}, ingested when W has no store "
                         "(Diffusion Policy's pusht.zip unpacks to pusht/)")
    ap.add_argument("--plot", type=Path, default=None,
                    help="also draw score and drift against rounds to this PNG")
    ap.add_argument("--plot-from", type=Path, default=None, metavar="RESULT.json",
                    help="only print the tables of a finished study's rounds.json, and draw "
                         "--plot from it (nothing is run)")
    args = ap.parse_args()
    if args.plot_from is not None:  # a finished study: its tables, and the plot if asked
        result = json.loads(args.plot_from.read_text())
        print(render(result))
        if result.get("sweeps"):
            print("\n" + render_sweeps(result))
        if args.plot is not None:
            plot(result, args.plot)
        return
    ws = args.workspace.resolve()
    ws.mkdir(parents=True, exist_ok=True)
    if not (ws / "dataset.zarr").exists():
        sefa(ws, "ingest", str(args.data / PUSHT_FILE), "--fps", "10", "--key", "keypoint", "--key", "state",
             "--key", "action")
    write_pipeline(ws, args)
    if args.base_from is not None:
        seed_base(ws, args.base_from.resolve())
    # the same preset and overrides as sefa.yaml names, so the cached base flow stays cached
    sefa(ws, "train", str(REPO / "pipelines" / "pusht_lowdim_train.yaml"), *train_overrides(args))
    rows = build_rows(ws, args)
    sweeps = build_sweeps(ws, args)
    base = rollout(ws, "train", args, ["--solver", "rk45"], n_test=args.base_n_test)
    by_slug = {}
    for row in rows + sweeps:
        row.update(rollout(ws, f"rows/{row['slug']}", args, []))
        by_slug[row["slug"]] = row
    unaligned = {r["round"]: r for r in rows if r["variant"] == "unaligned"}
    for row in rows:
        row["vs_base"] = paired(row["per_seed"], base["per_seed"])
        row["vs_unaligned"] = paired(row["per_seed"], unaligned[row["round"]]["per_seed"])
    for row in sweeps:
        row["vs_base"] = paired(row["per_seed"], base["per_seed"])
        ref = (by_slug[f"K{row['samples']}_unaligned_r1"] if row["sweep"] == "K"
               else unaligned[1])
        row["vs_unaligned"] = paired(row["per_seed"], ref["per_seed"])
    result = {"settings": vars(args) | {"workspace": str(ws)}, "base_rk45": base, "rows": rows,
              "sweeps": sweeps}
    atomic.write_text(ws / "rounds.json", json.dumps(result, indent=2, default=str))
    print(render(result))
    if sweeps:
        print("\n" + render_sweeps(result))
    if args.plot is not None:
        plot(result, args.plot)


def render_sweeps(result: dict) -> str:
    """Round 1's eps and K sweeps: each student against the base flow and against the unaligned
    student of the same couplings (for eps: the study's own round 1)."""
    s = result["settings"]
    pm = lambda d: f"{d[0]:+.3f}" + ("" if d[1] is None else f" ± {d[1]:.3f}")
    lines = ["| sweep | K | eps | couplings | score | success | - base RK45 | - unaligned (same couplings) | "
             "replaced (within eps) | drift mean |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in result["sweeps"]:
        eps = r["eps"]
        within = r["drift"]["within"].get(f"{eps:g}") if eps is not None else None
        lines.append(f"| {r['sweep']} | {r['samples']} | {'-' if eps is None else f'{eps:g}'} | "
                     f"{s['windows'] * r['samples']:,} | {r['score']:.3f} | {r['success']:.1%} | "
                     f"{pm(r['vs_base'])} | {pm(r['vs_unaligned'])} | "
                     f"{'-' if within is None else f'{within:.1%}'} | {r['drift']['mean']:.3f} |")
    return "\n".join(lines)


def plot(result: dict, out: Path) -> None:
    """Two panels against the reflow round: each variant's one-step score (± its paired standard
    error against the base flow) beside the base flow's RK45 score, and the couplings' drift from
    the expert chunks (mean distance, and the fraction within eps)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s, base = result["settings"], result["base_rk45"]
    fig, (ax_score, ax_drift) = plt.subplots(1, 2, figsize=(10, 4))
    for variant, marker, label in (("unaligned", "o", "unaligned"),
                                   ("aligned_final", "s", "aligned before distillation"),
                                   ("aligned_rounds", "^", "aligned every round")):
        rows = sorted((r for r in result["rows"] if r["variant"] == variant), key=lambda r: r["round"])
        if not rows:
            continue
        ax_score.errorbar([r["round"] for r in rows], [r["score"] for r in rows],
                          yerr=[r["vs_base"][1] or 0 for r in rows], marker=marker, capsize=3,
                          label=f"{label}, one step")
    ax_score.axhline(base["score"], color="k", ls="--", label="base flow, RK45")
    ax_score.set(xlabel="reflow round", ylabel=f"Push-T score ({s['n_test']} seeds)",
                 title="one-step students", xticks=range(1, int(s["rounds"]) + 1))
    ax_score.legend(fontsize=8)
    twin = ax_drift.twinx()
    for variant, label, color in (("unaligned", "unaligned", "tab:blue"),
                                  ("aligned_rounds", "aligned every round", "tab:green")):
        rows = sorted((r for r in result["rows"] if r["variant"] == variant), key=lambda r: r["round"])
        rounds = [r["round"] for r in rows]
        ax_drift.plot(rounds, [r["drift"]["mean"] for r in rows], "o-", color=color,
                      label=f"{label}: mean distance")
        twin.plot(rounds, [100 * r["drift"]["within"][f"{s['eps']:g}"] for r in rows], "s--",
                  color=color, alpha=0.6, label=f"{label}: % within eps {s['eps']:g}")
    ax_drift.set(xlabel="reflow round", ylabel="mean distance to the expert chunk (normalized)",
                 title="couplings' drift from the expert", xticks=range(1, int(s["rounds"]) + 1))
    twin.set_ylabel(f"% of couplings within eps {s['eps']:g} (dashed)")
    ax_drift.legend(loc="upper left", fontsize=7)
    twin.legend(loc="lower left", fontsize=7)
    fig.tight_layout()
    with atomic.writing(Path(out)) as tmp:
        fig.savefig(tmp, dpi=90, format="png")
    plt.close(fig)
    print(f"written: {out}")


def render(result: dict) -> str:
    s, base = result["settings"], result["base_rk45"]
    pm = lambda d: f"{d[0]:+.3f}" + ("" if d[1] is None else f" ± {d[1]:.3f}")
    lines = [f"Base flow RK45: score {base['score']:.3f}, success {base['success']:.1%} "
             f"({len(base['per_seed'])} seeds; students {s['n_test']}, paired over the seeds both ran). Couplings: {s['windows']} windows x K = {s['samples']}; "
             f"drift and 'within' use eps {s['eps']:g} (normalized units).", "",
             "| variant | round | score | success | - base RK45 | - unaligned (same round) | "
             "RK45 NFE per solve | drift mean | within eps |", "|---|---|---|---|---|---|---|---|---|"]
    for r in result["rows"]:
        within = r["drift"]["within"].get(f"{s['eps']:g}")
        lines.append(f"| {r['variant']} | {r['round']} | {r['score']:.3f} | {r['success']:.1%} | "
                     f"{pm(r['vs_base'])} | {pm(r['vs_unaligned'])} | {r['nfe_per_solve']:.0f} | "
                     f"{r['drift']['mean']:.3f} | {'' if within is None else f'{within:.1%}'} |")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
