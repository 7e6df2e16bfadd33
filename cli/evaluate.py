"""Evaluations: `sefa eval` (closed-loop rollouts or offline metrics, cached in WORKSPACE/evals/)
and `sefa results` (every evaluation kept there). Registered on the main app by cli/main.py; the
work is in pipelines/evals.py."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Optional

import typer

from sefa_data.errors import SefaInputError

from sefa_cli.params import (Decay, Device, EnsembleK, Execution, JsonFlag, ReplanEvery, Threads,
                             Weak, Workspace, start_process, workspace_device)
from sefa_cli.paths import in_workspace


def eval_(
    checkpoints: Annotated[Optional[list[Path]], typer.Argument(help="Checkpoints or run dirs, a relative one looked for in the workspace first (default: every stage of the workspace).")] = None,
    offline: Annotated[bool, typer.Option("--offline", help="Validation action MSE and multimodality on the store (no simulator).")] = False,
    env: Annotated[Optional[str], typer.Option(help="Closed-loop rollouts in simulation: pusht, robosuite:Lift, metaworld:TASK (reach, pick-place, ...) or metaworld:GROUP (easy, medium, hard, very_hard, all).")] = None,
    n_test: Annotated[int, typer.Option(help="Rollout episodes (test seeds from --start-seed).")] = 50,
    start_seed: Annotated[int, typer.Option(help="First test seed (Diffusion Policy: 100000).")] = 100000,
    max_steps: Annotated[Optional[int], typer.Option(help="Environment steps per rollout (default: Push-T and Lift 300, Meta-World its own 500).")] = None,
    solver: Annotated[Optional[str], typer.Option(help="Override the checkpoint's solver (flow: euler, midpoint, rk4, rk45, rk45-ps, dop853-ps; diffusion baseline: ddpm, ddim).")] = None,
    steps: Annotated[Optional[int], typer.Option(help="Steps for a fixed-step solver or the diffusion sampler.")] = None,
    windows: Annotated[Optional[int], typer.Option(help="Validation windows to evaluate, evenly spread. Default: the ones training validated on (the checkpoint's training.val_sample_windows), with its seed, so the action MSE is training's validation action MSE.")] = None,
    samples: Annotated[Optional[int], typer.Option(help="--offline: samples per observation for the multimodality measure [default: 8]. Rollouts with --execution coherent or bid: chunks drawn per decision in one batched call [default: 16].")] = None,
    execution: Execution = None,
    replan_every: ReplanEvery = None,
    decay: Decay = None,
    ensemble_k: EnsembleK = None,
    weak: Weak = None,
    key_map: Annotated[Optional[list[str]], typer.Option("--key-map", help="Rollouts: NAME=KEY feeds the simulator's observation NAME (Push-T: keypoint, state, agent_pos, img) to the policy's KEY, as `sefa serve --key-map` maps a client's names. LeRobot's Push-T names (observation.image, observation.state) are mapped without it. Repeatable.")] = None,
    out: Annotated[Optional[Path], typer.Option("--out", "-o", help="Rollouts: also write eval_log.json to this folder (one checkpoint). Every result is kept in WORKSPACE/evals/<mode>-<key>/ regardless.")] = None,
    force: Annotated[bool, typer.Option(help="Evaluate again even if this evaluation is cached.")] = False,
    device: Device = None,
    threads: Threads = None,
    workspace: Workspace = Path("."),
    as_json: JsonFlag = False,
) -> None:
    """Evaluate checkpoints: closed-loop rollouts (--env) or action MSE, NFE and sample spread on the store (--offline).

    Results are cached by (checkpoint content, solver, seeds, settings) in WORKSPACE/evals/: the
    same evaluation again is instant, other seeds or solvers get their own folder; `sefa
    results` lists them all. Under torchrun the rollout seeds are split across the processes;
    rank 0 writes the log.

    Example: sefa eval --env pusht --n-test 10 -w ws   |   sefa eval --offline -w ws"""
    from sefa_cli.console import TrainProgress
    from sefa_pipelines.evals import (EvalRequest, check_request, default_checkpoints, evaluate,
                                 result_rows)
    from sefa_model.distributed import context

    from sefa_pipelines.options import check_options, execution_option, key_map_option

    names = key_map_option(key_map, "a simulator's observation name")
    env = check_request(env, offline, names)
    check_options("eval", {"--n-test": n_test, "--start-seed": start_seed, "--max-steps": max_steps,
                           "--steps": steps, "--windows": windows,
                           "--samples": samples if env is None else None})
    asked = None
    if env is not None:
        asked = execution_option(execution, replan_every, samples, decay, ensemble_k, weak)
    elif any(v is not None for v in (execution, replan_every, decay, ensemble_k, weak)):
        raise SefaInputError("it and its options (--replan-every, --decay, --ensemble-k, "
                             "--weak) apply to rollouts (--env) only", key="--execution")
    start_process(device, threads, workspace)
    device = device or workspace_device(workspace)
    main_rank = context().is_main
    request = EvalRequest(env, n_test, start_seed, max_steps, solver, steps, windows,
                          8 if samples is None else samples, tuple(names.items()), asked)
    checkpoints = ([in_workspace(workspace, c) for c in checkpoints] if checkpoints
                   else default_checkpoints(workspace))
    with TrainProgress(enabled=main_rank and not as_json) as progress:
        records = evaluate(workspace, checkpoints, request, device=device, force=force, out=out,
                           is_main=main_rank, log=progress.log)
    if not main_rank:
        return
    rows = result_rows(workspace, records, env)
    if as_json:
        print(json.dumps(rows, indent=2))
    elif env is not None:
        for log in rows:
            print(f"{log['checkpoint']}: {log['kind']}, {log['solver']}, "
                  f"{log.get('execution_label', 'receding (n_action_steps)')}: mean score "
                  f"{log['test/mean_score']:.3f}, success {log['test/success_rate']:.0%} over "
                  f"{log['n_test']} seeds from {log['test_start_seed']} ({log['eval_log']})")
    else:
        _offline_table(rows)


def _offline_table(rows: list[dict]) -> None:
    from rich.table import Table

    from sefa_cli.console import out as console_out

    first = rows[0] if rows else {}
    t = Table(title=f"offline evaluation ({first.get('windows', '')} {first.get('split', '')} "
                    f"windows, {first.get('samples', '')} samples each)")
    for col in ("checkpoint", "kind", "solver", "NFE", "action MSE", "mean-action MSE",
                "best-of-K MSE", "spread / expert"):
        t.add_column(col)
    notes = set()
    for r in rows:
        mean = r.get("mean_action_mse")
        spread = f"{r['spread']:.3f} / {r['expert_spread']:.3f}"
        if r.get("spread_note"):
            spread += " (no ratio)"
            notes.add(r["spread_note"])
        t.add_row(r["checkpoint"], r["kind"], f"{r['solver']}{'' if r['steps'] is None else '-' + str(r['steps'])}",
                  str(r["nfe"]), f"{r['action_mse']:.4g}", "-" if mean is None else f"{mean:.4g}",
                  f"{r['action_mse_best_of_k']:.4g}", spread)
    console_out.print(t)
    # the one row worth a sentence: the baseline beating the policies
    beaten = [r["checkpoint"] for r in rows if r.get("mean_action_mse") is not None
              and r["mean_action_mse"] <= r["action_mse"]]
    if beaten:
        console_out.print(f"always predicting the training set's mean action beats "
                          f"{', '.join(beaten)} on these windows")
    for note in sorted(notes):
        console_out.print(note)
    if rows:
        console_out.print("action MSE: sample 0 of each window, training's validation definition "
                          "(the same windows and noise as training's with the default --windows)")


def choose_execution(
    checkpoint: Annotated[Path, typer.Argument(help="The checkpoint or run dir to choose for (e.g. distill).")],
    env: Annotated[str, typer.Option(help="The simulator to choose in: pusht, robosuite:Lift, metaworld:TASK.")],
    n_val: Annotated[int, typer.Option(help="Validation episodes per candidate.")] = 50,
    val_start_seed: Annotated[int, typer.Option(help="First validation seed; never one of the test seeds (100000..199999).")] = 200000,
    max_steps: Annotated[Optional[int], typer.Option(help="Environment steps per episode (default: the simulator's, as sefa eval).")] = None,
    solver: Annotated[Optional[str], typer.Option(help="The sampler setting to choose for (default: the checkpoint's).")] = None,
    steps: Annotated[Optional[int], typer.Option(help="Steps of that solver.")] = None,
    budget_ms: Annotated[Optional[float], typer.Option(help="Largest time one decision may take where the command runs, its p99, ms (default: the control period, 1000 / fps).")] = None,
    fps: Annotated[Optional[float], typer.Option(help="The task's control rate (default: the policy's store's).")] = None,
    candidates: Annotated[Optional[list[str]], typer.Option("--candidate", help="An execution to try, MODE[-K][xN] (receding-4, ensemble-1, coherent-1x16, bid-1x16); repeatable. Default: receding every 1, 2, 4 and n_action_steps steps, ensemble-1, coherent-1/2/4x16, and bid likewise with --weak.")] = None,
    weak: Weak = None,
    min_gain_se: Annotated[float, typer.Option(help="Leave the default (n_action_steps actions a prediction) only for an execution this many paired standard errors above it on the validation seeds; 0: the best mean.")] = 2.0,
    force: Annotated[bool, typer.Option(help="Roll out again even where a validation result is cached.")] = False,
    device: Device = None,
    threads: Threads = None,
    workspace: Workspace = Path("."),
    as_json: JsonFlag = False,
) -> None:
    """Choose how a policy executes its chunks: try every execution that fits the latency budget on validation seeds (never the test seeds), keep the best with the policy (the default unless the best beats it by --min-gain-se standard errors).

    sefa eval, sefa serve, sefa export and the LeRobot integration then run it by default
    (execution.json in the checkpoint). Prints each candidate's decision time, per-step
    cost and validation score, and what choosing cost.

    Example: sefa choose-execution distill --env pusht --n-val 50 -w ws"""
    from sefa_cli.console import TrainProgress
    from sefa_pipelines.choose import ChooseRequest, choose, with_weak
    from sefa_pipelines.evals import check_request
    from sefa_pipelines.options import check_options
    from sefa_pipelines.choose import check_validation_seeds

    env = check_request(env, False)
    check_options("choose", {"--n-val": n_val, "--val-start-seed": val_start_seed,
                             "--max-steps": max_steps, "--steps": steps,
                             "--budget-ms": budget_ms, "--fps": fps,
                             "--min-gain-se": min_gain_se})
    check_validation_seeds(val_start_seed, n_val)
    if candidates:
        from sefa_model.policy.execution import parse_spec

        for spec in candidates:
            parse_spec(spec, weak).check(100_000)
    start_process(device, threads, workspace)
    device = device or workspace_device(workspace)
    request = with_weak(ChooseRequest(env, n_val, val_start_seed, max_steps, solver, steps,
                                      budget_ms, fps, tuple(candidates or ()), weak,
                                      min_gain_se), workspace)
    with TrainProgress(enabled=not as_json) as progress:
        summary = choose(workspace, in_workspace(workspace, checkpoint), request, device=device,
                         log=progress.log, force=force)
    if as_json:
        print(json.dumps(summary, indent=2))
        return
    _choice_table(summary)


def _choice_table(s: dict) -> None:
    from rich.table import Table

    from sefa_cli.console import out as console_out

    t = Table(title=f"executions on {s['env']}, validation seeds {s['validation_seeds'][0]}.."
                    f"{s['validation_seeds'][1]} (control period {1000 / s['fps']:.3g} ms, "
                    f"budget {s['budget_ms']:.3g} ms a decision)")
    for col in ("execution", "decision ms", "mean ms / step", "validation score", "- default"):
        t.add_column(col, justify="left" if col == "execution" else "right")
    for r in s["candidates"]:
        score = "over budget" if not r["within_budget"] else f"{r['mean_score']:.3f}"
        diff = ("" if r.get("minus_default") is None else f"{r['minus_default']:+.3f}"
                + ("" if r.get("minus_default_se") is None else f" ± {r['minus_default_se']:.3f}"))
        t.add_row(r["label"] + ("  <- chosen" if r["label"] == s["chosen"] else ""),
                  f"{r['decision_ms']:.3g}", f"{r['mean_step_ms']:.3g}", score, diff)
    console_out.print(t)
    console_out.print(f"chosen: {s['chosen']}, {s['why']} (kept in {s['record']}); choosing took "
                      f"{s['seconds']:.0f} s, {s['episodes_run']} validation episodes run here",
                      highlight=False)


Against = Annotated[Optional[str], typer.Option("--against", help="The reference: CHECKPOINT or CHECKPOINT@SOLVER (e.g. train@rk45). Default: the base flow's evaluation with the most network evaluations a chunk (the teacher).")]


def compare(against: Against = None, workspace: Workspace = Path("."),
            as_json: JsonFlag = False) -> None:
    """Each closed-loop evaluation minus the reference's (the teacher), paired over the seeds both ran, ± its standard error, beside the ratio of their decision latencies.

    The seeds' difficulty cancels in a paired difference; latencies are the p50 of the
    decisions the rollouts timed, compared only at the same torch threads.

    Example: sefa eval train --solver rk45 --env pusht -w ws; sefa eval distill --env pusht -w ws; sefa compare -w ws"""
    from sefa_pipelines.comparison import workspace_comparisons

    rows = workspace_comparisons(workspace, against)
    if as_json:
        print(json.dumps(rows, indent=2))
        return
    if not rows:
        print("nothing to compare: evaluate the base flow and another policy in the same "
              "simulator on the same seeds (sefa eval train --solver rk45 --env pusht; "
              "sefa eval distill --env pusht)" + (f"; no evaluation of {against}" if against else ""))
        return
    _comparison_table(rows)


def _comparison_table(rows: list[dict]) -> None:
    from rich.table import Table

    from sefa_cli.console import out as console_out

    for ref in dict.fromkeys((r["env"], r["reference"]) for r in rows):
        group = [r for r in rows if (r["env"], r["reference"]) == ref]
        t = Table(title=f"against {ref[1]} in {ref[0]}, paired over the seeds both ran")
        for col in ("policy", "execution", "seeds", "score", "reference", "difference ± SE",
                    "decision p50 ms", "latency ratio"):
            t.add_column(col, justify="left" if col in ("policy", "execution") else "right")
        for r in group:
            se = "" if r["difference_se"] is None else f" ± {r['difference_se']:.3f}"
            ms = r["decision_ms"]
            ratio = "-" if r["latency_ratio"] is None else f"{r['latency_ratio']:.3g}"
            t.add_row(r["policy"], r["execution"] or "-", str(r["paired_seeds"]),
                      f"{r['score']:.3f}", f"{r['reference_score']:.3f}",
                      f"{r['difference']:+.3f}{se}", "-" if not ms else f"{ms['p50_ms']:.3g}",
                      ratio)
        console_out.print(t)
        ref_ms = group[0]["reference_decision_ms"]
        if ref_ms:
            console_out.print(f"{ref[1]}: decision p50 {ref_ms['p50_ms']:.3g} ms over "
                              f"{ref_ms['decisions']} decisions, {ref_ms['threads']} torch "
                              "threads", highlight=False, markup=False)
        for note in sorted({r["latency_note"] for r in group if r["latency_note"]}):
            console_out.print(f"latency ratio not given: {note}", highlight=False, markup=False)


def results(workspace: Workspace = Path("."), as_json: JsonFlag = False) -> None:
    """Every evaluation kept in the workspace (WORKSPACE/evals/), one row each; then each closed-loop one against the base flow's, paired over the seeds both ran (as `sefa compare`).

    Example: sefa results -w ws"""
    from rich.table import Table

    from sefa_cli.console import out as console_out
    from sefa_pipelines.evals import all_results

    rows = all_results(workspace)
    if as_json:
        print(json.dumps(rows, indent=2))
        return
    if not rows:
        print("no evaluations yet: sefa eval --offline, or sefa eval --env pusht")
        return
    cells = [_result_cells(r) for r in rows]
    t = Table(title=f"evaluations in {workspace}/evals")
    for col in cells[0]:
        # names are copied into the next command: never cut (the result column wraps instead)
        t.add_column(col, no_wrap=col in WHOLE_CELLS)
    for c in cells:
        t.add_row(*c.values())
    if _narrowest_table(cells) > console_out.width:
        # too narrow for the table (an 80-column terminal): one evaluation per two lines
        for c in cells:
            console_out.print(f"{c['folder']}  {c['checkpoint (run)']}  {c['kind']}, {c['mode']}, "
                              f"{c['solver']}, {c['execution']}, NFE {c['NFE']}\n"
                              f"    {c['result']} ({c['when']})",
                              highlight=False, markup=False, soft_wrap=True)
    else:
        console_out.print(t)
    from sefa_pipelines.comparison import workspace_comparisons

    compared = workspace_comparisons(workspace)
    if compared:
        _comparison_table(compared)


WHOLE_CELLS = ("checkpoint (run)", "folder")


def _narrowest_table(cells: list[dict[str, str]]) -> int:
    """The columns a table of these cells needs at the least: whole names unbroken, the other
    cells wrapped at spaces (rich squeezes a narrower table into empty columns)."""
    def least(col: str, text: str) -> int:
        return len(text) if col in WHOLE_CELLS else max(map(len, text.split()), default=0)
    return 1 + sum(3 + max(least(col, col), *(least(col, c[col]) for c in cells))
                   for col in cells[0])


def _result_cells(r: dict) -> dict[str, str]:
    """One evaluation as `sefa results` prints it, column by column."""
    from sefa_pipelines.evals import key_metric

    res = r["result"]
    if r["mode"] == "offline":
        metric = key_metric(r)
        nfe = str(res["nfe"])
    else:
        metric = (f"score {res['test/mean_score']:.3f}, success {res['test/success_rate']:.0%} "
                  f"({res['n_test']} seeds from {res['test_start_seed']})")
        if res.get("decision_ms"):  # what the rollouts' decisions took (older logs: untimed)
            metric += f"; decision p50 {res['decision_ms']['p50_ms']:.3g} ms"
        # per predicted chunk, the mean over the rollouts (older logs did not record it)
        nfe = "-" if res.get("nfe") is None else f"{res['nfe']:g}"
    solver = res.get("solver") or "-"
    if r["mode"] == "offline" and res.get("steps") is not None:
        solver += f"-{res['steps']}"
    # rollouts before executions were chosen ran receding horizon over n_action_steps
    execution = "-" if r["mode"] == "offline" else res.get("execution_label", "receding (all)")
    return {"checkpoint (run)": f"{r['checkpoint']} ({r['checkpoint_run']})",
            "kind": res.get("kind", "-"), "mode": r["mode"], "solver": solver,
            "execution": execution, "NFE": nfe,
            "result": metric, "when": r["created"].replace("T", " ")[:16], "folder": r["folder"]}
