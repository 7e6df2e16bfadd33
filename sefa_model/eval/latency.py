"""Batch-1 inference latency: what a robot waits for per action chunk (`sefa bench latency`).

For each target `CHECKPOINT[@SOLVER[-STEPS]]` (no setting: the checkpoint's own) this times
`Policy.predict_action` on one observation, the whole call a controller makes (normalization,
encoder, every network evaluation of the sampler, unnormalization), after warm-up calls, and
reports p50 / p90 / p99. On the same prepared tensors it also times the pieces: the observation
encoder alone, one action-head evaluation alone, and one bare forward pass (encoder + one head
evaluation, i.e. `model(obs, x, t)`), the floor that no sampler of this network can beat. The
four take turns call by call, so a change of load on the machine shifts them alike.

The observation is a real validation window of the store when one is given (an adaptive solver's
NFE depends on it), else the centre of the normalizer's range. The starting noise is fixed, so
an adaptive solver takes the same steps in every call. On CUDA every timer synchronises the
device before it reads the clock.
"""

from __future__ import annotations

import os

import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from sefa_data.errors import SefaInputError
from sefa_model.policy.processor import lowdim_view
from sefa_model.policy.artifact import Policy
from sefa_model.distributed import load_average
from sefa_model.policy.sampling import resolve_solver


@dataclass
class LatencyRow:
    target: str
    checkpoint: str
    kind: str
    setting: str  # e.g. rk45, euler-1, ddpm-100, ddim-10
    nfe: int
    calls: int
    p50_ms: float
    p90_ms: float
    p99_ms: float
    encoder_ms: float  # p50 of the observation encoder alone
    head_ms: float  # p50 of one action-head evaluation alone
    forward_ms: float  # p50 of one bare forward pass (encoder + one head evaluation)
    obs_source: str

    @property
    def ratio_to_forward(self) -> float:
        return self.p50_ms / self.forward_ms


def parse_target(target: str) -> tuple[str, str | None, int | None]:
    """'runs/x/train@ddim-10' -> ('runs/x/train', 'ddim', 10); no '@': the checkpoint's own."""
    path, _, setting = target.partition("@")
    if not setting:
        return path, None, None
    solver, _, steps = setting.partition("-")
    if steps and not steps.isdigit():
        raise SefaInputError(f"'{target}': the setting must be SOLVER or SOLVER-STEPS, e.g. "
                             "euler-1, ddim-10, rk45", key="target")
    return path, solver, int(steps) if steps else None


# What decides whether an execution fits a control period, everywhere (`sefa bench latency`,
# `sefa serve`, `sefa choose-execution`): a controller that predicts synchronously waits a
# whole decision at each replanning step, so the decision's p99 must fit, not its median.
FIT_PERCENTILE = "p99_ms"


def percentiles_ms(seconds: np.ndarray) -> tuple[float, float, float]:
    p50, p90, p99 = np.percentile(seconds, [50, 90, 99]) * 1e3
    return float(p50), float(p90), float(p99)


def named_percentiles_ms(seconds: np.ndarray) -> dict[str, float]:
    """percentiles_ms by name: p50_ms, p90_ms, p99_ms (FIT_PERCENTILE is one of them)."""
    return dict(zip(("p50_ms", "p90_ms", "p99_ms"), percentiles_ms(seconds)))


def time_calls(fns: dict[str, Callable[[], object]], *, warmup: int, calls: int,
               max_seconds: float, sync: Callable[[], None], warmup_seconds: float = 0.0
               ) -> dict[str, np.ndarray]:
    """Seconds per call of each function, after `warmup` untimed rounds. The functions take
    turns call by call, so that a load change on the machine hits all of them alike and their
    ratios stay meaningful; stops early (after at least min(calls, 20) rounds) once
    `max_seconds` have passed, for the slow settings."""
    # at least `warmup` rounds and `warmup_seconds`: the first timings of a fresh process run
    # several times slower for about a second (thread pools, caches, clock ramp-up)
    warm_end = time.perf_counter() + warmup_seconds
    done = 0
    while done < warmup or time.perf_counter() < warm_end:
        for fn in fns.values():
            fn()
        done += 1
    sync()
    out: dict[str, list[float]] = {name: [] for name in fns}
    budget_end = time.perf_counter() + max_seconds
    for i in range(calls):
        for name, fn in fns.items():
            start = time.perf_counter()
            fn()
            sync()
            out[name].append(time.perf_counter() - start)
        if i + 1 >= min(calls, 20) and time.perf_counter() > budget_end:
            break
    return {name: np.asarray(v) for name, v in out.items()}


def example_observation(policy: Policy, store: Path | None) -> tuple[dict, str]:
    """One observation history (batch 1) in the store's raw units."""
    cfg = policy.cfg
    if store is not None and Path(store).exists():
        from sefa_data.store.zarr_store import EpisodeStore
        from sefa_model.data.windows import PolicyData

        data = PolicyData(cfg, EpisodeStore.open(store), policy.normalizer)
        sampler = data.valid or data.train
        batch = sampler.batch(np.array([len(sampler) // 2]))
        return {k: batch[k] for k in cfg.shape_meta.obs}, f"window {len(sampler) // 2} of {store}"
    obs = {}
    for key, spec in cfg.shape_meta.obs.items():
        if spec.type == "rgb":
            frame = np.full(spec.frame_shape, 128, np.uint8)
        else:
            frame = np.zeros(spec.frame_shape, np.float32)
            # which elements of a stored frame the policy sees (its `dims` slice, flattened)
            seen = lowdim_view(key, spec, np.arange(frame.size).reshape(1, 1, *frame.shape))[0, 0]
            frame.flat[seen] = policy.normalizer.unnormalize(key, np.zeros(len(seen), np.float32))
        obs[key] = np.broadcast_to(frame, (1, cfg.policy.n_obs_steps, *frame.shape)).copy()
    return obs, "the centre of the normalizer's range"


@torch.inference_mode()  # as predict_action runs, so that the floor is measured alike
def measure(target: str, *, store: Path | None = None, device: str = "cpu", calls: int = 200,
            warmup: int = 20, max_seconds: float = 20.0, warmup_seconds: float = 1.0,
            policy: Policy | None = None) -> LatencyRow:
    path, solver, steps = parse_target(target)
    policy = policy or Policy.load(path, device=device)
    cfg = policy.cfg
    solver, steps = resolve_solver(cfg, solver, steps)
    setting = solver if steps is None else f"{solver}-{steps}"
    obs, source = example_observation(policy, store)
    dev = policy.device
    sync = (lambda: torch.cuda.synchronize(dev)) if dev.type == "cuda" else (lambda: None)
    shape = (1, cfg.policy.horizon, cfg.shape_meta.action.shape[-1])
    noise = torch.randn(shape, generator=torch.Generator().manual_seed(0))

    nfe = policy.predict_action(obs, solver=solver, steps=steps, noise=noise).nfe
    model = policy.model
    o = policy.prepare_obs(obs)
    x = noise.to(dev)
    t = model.method.probe_time(cfg, dev)
    cond = model.encode(o)
    head = lambda x, t, cond: model.method.network(model, x, t, cond)  # noqa: E731
    times = time_calls({"total": lambda: policy.predict_action(obs, solver=solver, steps=steps, noise=noise),
                        "encoder": lambda: model.encode(o),
                        "head": lambda: head(x, t, cond),
                        "forward": lambda: model(o, x, t)},
                       warmup=warmup, calls=calls, max_seconds=max_seconds, sync=sync,
                       warmup_seconds=warmup_seconds)
    p50, p90, p99 = percentiles_ms(times["total"])
    median = {name: percentiles_ms(v)[0] for name, v in times.items()}
    return LatencyRow(target=target, checkpoint=policy.path, kind=policy.kind, setting=setting,
                      nfe=nfe, calls=len(times["total"]), p50_ms=p50, p90_ms=p90, p99_ms=p99,
                      encoder_ms=median["encoder"], head_ms=median["head"],
                      forward_ms=median["forward"], obs_source=source)


def bench_latency(targets: list[str], *, store: Path | None = None, device: str = "auto",
                  calls: int = 200, warmup: int = 20, max_seconds: float = 20.0, passes: int = 1,
                  log: Callable[[str], None] = lambda _: None, compile: bool = False,
                  sample_sizes: tuple[int, ...] = (), fps: float | None = None) -> dict:
    """Every target in one process, one after another, with the machine described. With
    `passes` > 1 the targets are timed that many times in turn and each keeps its fastest pass
    (by p50), so that a slow spell of a shared machine does not land on one target only.
    With `sample_sizes`, also one decision of N samples per target and N (`decisions`) and
    what each execution costs per control step at `fps` (`executions`; default fps: the
    store's)."""
    from sefa_data.bench.throughput import machine_description

    from sefa_model.distributed import busy_cpu_note, resolve_device

    device = str(resolve_device(device))
    loaded: dict[str, Policy] = {}
    for target in targets:  # every target checked before anything is timed
        path, solver, steps = parse_target(target)
        if path not in loaded:
            loaded[path] = Policy.load(path, device=device)
            if compile:
                loaded[path].compile()
        try:
            resolve_solver(loaded[path].cfg, solver, steps)
        except SefaInputError as e:
            raise SefaInputError(e.what, file=target) from None
    busy = busy_cpu_note(torch.device(device), torch.get_num_threads(), load_average(),
                         os.cpu_count())
    if busy:
        log(busy)
    best: dict[str, LatencyRow] = {}
    for n in range(max(1, passes)):
        for target in targets:
            log(f"timing {target}" + (f" (pass {n + 1} of {passes})" if passes > 1 else ""))
            row = measure(target, store=store, device=device, calls=calls, warmup=warmup,
                          max_seconds=max_seconds, policy=loaded[parse_target(target)[0]])
            if target not in best or row.p50_ms < best[target].p50_ms:
                best[target] = row
    rows = [{**asdict(best[t]), "ratio_to_forward": best[t].ratio_to_forward} for t in targets]
    for row in rows:
        note = spread_note(row, load_average(), os.cpu_count())
        if note:
            log(note)
    machine = machine_description()
    if device.startswith("cuda"):
        machine["gpu"] = torch.cuda.get_device_name(torch.device(device))
    out = {"machine": machine, "device": device, "batch": 1, "warmup": warmup, "calls": calls,
           "passes": passes, "compiled": compile, "threads": torch.get_num_threads(),
           "load_average": load_average(), "rows": rows}
    if sample_sizes:
        out.update(decisions_and_executions(targets, loaded, sample_sizes, store, fps, max_seconds,
                                            log))
    else:  # the executions of one chunk a decision, from the batch-1 timings just taken
        fps = control_rate(fps, store)
        out.update({"fps": fps, "executions": [
            {"target": row["target"], **cost}
            for row in rows for cost in single_chunk_costs(
                loaded[parse_target(row["target"])[0]].cfg.policy.n_action_steps,
                row["p50_ms"], row["p99_ms"], fps)]})
    return out


def control_rate(fps: float | None, store: Path | None) -> float | None:
    """The rate a step must keep: `fps` when given, else the store's."""
    if fps is None and store is not None and Path(store).exists():
        from sefa_data.store.zarr_store import EpisodeStore

        fps = EpisodeStore.open(store).fps
    return fps


def single_chunk_costs(n_action_steps: int, decision_ms: float, worst_ms: float,
                       fps: float | None) -> list[dict]:
    """What each default execution that draws one chunk a decision (receding horizon at every
    replanning period, ACT's ensembling) costs per control step, from one batch-1 decision."""
    from sefa_model.policy.execution import candidates

    return [execution_cost(c, decision_ms, fps, worst_ms)
            for c in candidates(n_action_steps) if (c.samples or 1) == 1]


def fit_summary(executions: list[dict], fps: float | None) -> list[str]:
    """One line per target: at this control rate, which executions keep every step within the
    period (the worst step, p99, a whole decision) and which do not; [] with no rate known."""
    if not fps:
        return []
    lines, by_target = [], {}
    for e in executions:
        by_target.setdefault(e["target"], []).append(e)
    for target, rows in by_target.items():
        fit = [e["execution"] for e in rows if e["fits"]]
        miss = [f"{e['execution']} ({e['worst_step_ms']:.3g} ms)" for e in rows if not e["fits"]]
        text = f"{target} at {fps:g} Hz ({1000 / fps:.3g} ms a step): "
        text += ("fits: " + ", ".join(fit)) if fit else "no execution fits"
        if miss:
            text += "; over the period at its worst step: " + ", ".join(miss)
        lines.append(text)
    return lines


def decisions_and_executions(targets: list[str], loaded: dict[str, Policy],
                             sizes: tuple[int, ...], store: Path | None, fps: float | None,
                             max_seconds: float, log: Callable[[str], None]) -> dict:
    """`bench_latency`'s decision rows (one decision of N samples per target) and each
    default execution's cost per control step (sefa_model/policy/execution.py:candidates; bid
    needs a weaker policy and is left out) from the decision at its N: the mean from p50, the
    worst step from p99."""
    from sefa_model.policy.execution import candidates

    fps = control_rate(fps, store)
    decisions, executions = [], []
    for target in targets:
        path, solver, steps = parse_target(target)
        policy = loaded[path]
        log(f"timing {target} at {', '.join(map(str, sizes))} samples a decision")
        rows = decision_times(policy, sizes, solver=solver, steps=steps, store=store,
                              max_seconds=max_seconds)
        decisions += [{"target": target, "kind": policy.kind, **r} for r in rows]
        at = {r["samples"]: r for r in rows}
        for c in candidates(policy.cfg.policy.n_action_steps):
            if c.samples in at:
                executions.append({"target": target, **execution_cost(
                    c, at[c.samples]["p50_ms"], fps, at[c.samples][FIT_PERCENTILE])})
    return {"sample_sizes": list(sizes), "fps": fps, "decisions": decisions,
            "executions": executions}


# p99 over p50 beyond this: the timings are the machine's other work as much as the policy's
SPREAD_WARN = 3.0


def spread_note(row: dict, load: float | None, cores: int | None) -> str | None:
    """A line when a target's timings spread so far that its p50 is not to be trusted alone
    (other processes took the cores during the run): the spread, the load, what to do."""
    spread = row["p99_ms"] / max(row["p50_ms"], 1e-9)
    if spread < SPREAD_WARN:
        return None
    busy = (f"; the machine is busy (load {load:.1f} on {cores} cores)"
            if load is not None and cores and load >= cores else "")
    return (f"warning: {row['target']}: p99 is {spread:.1f}x p50 ({row['p99_ms']:.3g} vs "
            f"{row['p50_ms']:.3g} ms){busy}: the numbers include other work; rerun with "
            "--passes 3 (each target keeps its fastest pass) and --threads 1 on a shared CPU")


# ---- one decision at N samples, and what each execution costs per control step

SAMPLE_SIZES = (1, 4, 16, 64)


@torch.inference_mode()
def decision_times(policy: Policy, sizes: tuple[int, ...] = SAMPLE_SIZES, *,
                   solver: str | None = None, steps: int | None = None,
                   store: Path | None = None, calls: int = 50, warmup: int = 5,
                   max_seconds: float = 10.0) -> list[dict]:
    """Per N in `sizes`: p50 / p90 / p99 ms of one decision that draws N chunks for one
    observation in one batched call (`predict_action` on it with N noises, encoded once: what
    an execution choosing among N samples waits for). The sizes take turns call by call."""
    solver, steps = resolve_solver(policy.cfg, solver, steps)
    obs, _ = example_observation(policy, store)
    dev = policy.device
    sync = (lambda: torch.cuda.synchronize(dev)) if dev.type == "cuda" else (lambda: None)
    horizon, da = policy.cfg.policy.horizon, policy.cfg.shape_meta.action.shape[-1]
    gen = torch.Generator().manual_seed(0)
    fns = {}
    for n in sizes:
        noise = torch.randn((n, horizon, da), generator=gen)
        fns[n] = (lambda x=noise: policy.predict_action(obs, solver=solver, steps=steps,
                                                        noise=x))
    times = time_calls(fns, warmup=warmup, calls=calls, max_seconds=max_seconds, sync=sync)
    setting = solver if steps is None else f"{solver}-{steps}"
    return [{"samples": n, "setting": setting, "calls": len(times[n]),
             **named_percentiles_ms(times[n])}
            for n in sizes]


def execution_cost(settings, decision_ms: float, fps: float | None,
                   worst_ms: float | None = None) -> dict:
    """What an execution (resolved ExecutionSettings) costs per control step, given the time
    of one of its decisions (its N samples, the weaker policy's included; `worst_ms`, a high
    percentile of it, when known): the mean per step (decision / replan_every), the worst step
    (one decision: a controller that predicts synchronously waits that long at every
    replanning step) and whether that fits the control period 1000 / fps ms (None: no rate
    known)."""
    period = None if not fps else 1000.0 / fps
    worst = decision_ms if worst_ms is None else worst_ms
    return {"execution": settings.label, "decision_ms": decision_ms,
            "mean_step_ms": decision_ms / settings.replan_every, "worst_step_ms": worst,
            "period_ms": period, "fits": None if period is None else worst <= period}
