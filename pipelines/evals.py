"""Evaluations that last: each result in its own folder, cached by what it depends on.

    WORKSPACE/evals/<mode>-<key>/result.json     (and eval_log.json for rollouts)

`key` hashes the checkpoint's content (every file of the checkpoint directory) and the
evaluation's settings (solver, steps, seeds, windows, ...), so the same evaluation asked twice is
read back at once, different seeds or solvers sit side by side, and a retrained checkpoint is
evaluated anew. Paths are recorded relative to the workspace. A result folder is written under a
temporary name and renamed into place.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
from dataclasses import dataclass
from functools import partial
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Callable, Collection

from sefa_pipelines.runner import STATE_DIR, FileHashCache, canonical_json, path_sha256
from sefa_data import atomic
from sefa_data.errors import SefaInputError

EVALS_DIR = "evals"
RESULT = "result.json"


def checkpoint_sha256(workspace: Path, checkpoint: Path) -> str:
    """The checkpoint's content, the execution chosen for it left out (a result's key holds
    the execution it ran)."""
    from sefa_model.policy.checkpoint import SIDECAR_FILES, resolve_checkpoint

    cache = FileHashCache(workspace.absolute() / STATE_DIR / "file_hashes.json")
    try:
        return path_sha256(resolve_checkpoint(checkpoint), cache, exclude=tuple(SIDECAR_FILES))
    finally:
        cache.save()


def label(workspace: Path, path: Path) -> str:
    """A path as the workspace names it: relative when inside, else absolute."""
    try:
        return Path(os.path.abspath(path)).relative_to(workspace.absolute()).as_posix()
    except ValueError:
        return str(Path(path).absolute())


def eval_key(checkpoint_sha: str, mode: str, settings: dict[str, Any]) -> str:
    text = canonical_json({"checkpoint": checkpoint_sha, "mode": mode, "settings": settings})
    return hashlib.sha256(text.encode()).hexdigest()[:12]


def eval_dir(workspace: Path, mode: str, key: str) -> Path:
    return workspace / EVALS_DIR / f"{mode.replace(':', '_')}-{key}"


def cached_eval(workspace: Path, checkpoint: Path, mode: str, settings: dict[str, Any],
                run: Callable[[Path], dict[str, Any] | None], *, force: bool = False,
                is_main: bool = True) -> tuple[dict[str, Any] | None, bool]:
    """(the result record, whether it was computed now). `run(folder)` evaluates, may write
    files into `folder`, and returns the result (None on ranks other than 0)."""
    sha = checkpoint_sha256(workspace, checkpoint)
    key = eval_key(sha, mode, settings)
    final = eval_dir(workspace, mode, key)
    cached = read_result(final)
    if cached is not None and not force:
        return cached, False
    tmp = atomic.tmp_name(final)
    # the folders this evaluation creates (evals/ itself, the first time): a failed one leaves
    # the workspace as it found it
    made = [d for d in tmp.parents if d.is_relative_to(workspace) and not d.exists()]
    if is_main:
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir(parents=True)
    try:
        started = time.monotonic()
        result = run(tmp)
        if not is_main or result is None:
            return None, True
        real = os.path.realpath(checkpoint)
        record = {
            "mode": mode, "key": key, "settings": settings,
            "checkpoint": label(workspace, checkpoint), "checkpoint_run": label(workspace, Path(real)),
            "checkpoint_sha256": sha,
            "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "duration_s": round(time.monotonic() - started, 3),
            "result": _relative(result, workspace, tmp, final),
        }
        (tmp / RESULT).write_text(json.dumps(record, indent=2) + "\n")
        atomic.replace_dir(tmp, final)
        return record, True
    except BaseException:
        if is_main:
            shutil.rmtree(tmp, ignore_errors=True)
            for folder in made:  # innermost first; one that another run filled meanwhile stays
                try:
                    folder.rmdir()
                except OSError:
                    pass
        raise


def _relative(value: Any, workspace: Path, tmp: Path, final: Path) -> Any:
    if isinstance(value, dict):
        return {k: _relative(v, workspace, tmp, final) for k, v in value.items()}
    if isinstance(value, list):
        return [_relative(v, workspace, tmp, final) for v in value]
    if isinstance(value, str) and os.path.isabs(value):
        if value.startswith(str(tmp)):
            value = str(final) + value[len(str(tmp)):]
        return label(workspace, Path(value))
    return value


def read_result(folder: Path) -> dict[str, Any] | None:
    try:
        value = json.loads((folder / RESULT).read_text())
    except (OSError, ValueError):
        return None
    return value if isinstance(value, dict) else None


def all_results(workspace: Path) -> list[dict[str, Any]]:
    """Every evaluation kept in the workspace, oldest first, each with its folder."""
    root = workspace / EVALS_DIR
    rows = []
    for folder in sorted(root.iterdir()) if root.is_dir() else []:
        if folder.name.startswith("."):
            continue
        record = read_result(folder)
        if record is not None:
            rows.append({**record, "folder": label(workspace, folder)})
    return sorted(rows, key=lambda r: r.get("created", ""))


def spread_words(r: dict[str, Any]) -> str:
    """The spread against the expert's: a ratio, or why there is none (an expert spread of
    about zero; results kept before this was checked have a number there)."""
    if r.get("spread_ratio") is None:
        return f"spread {r['spread']:.3g}, expert spread {r['expert_spread']:.2g} (no ratio)"
    return f"spread ratio {r['spread_ratio']:.2f}"


def key_metric(record: dict[str, Any]) -> str:
    r = record["result"]
    if record["mode"] == "offline":
        mean = ("" if r.get("mean_action_mse") is None
                else f" (mean action {r['mean_action_mse']:.4g})")
        return (f"action MSE {r['action_mse']:.4g}{mean}, {spread_words(r)} "
                f"({r['windows']} {r['split']} windows)")
    return (f"mean score {r['test/mean_score']:.3f}, success {r['test/success_rate']:.0%} "
            f"({r['n_test']} seeds from {r['test_start_seed']})")


# --- `sefa eval`: what it evaluates by default, and how ------------------------------------------

ENVS = ("pusht", "robosuite:Lift")
METAWORLD = "metaworld:"  # + a task, a difficulty group or `all` (sefa_sim/metaworld.py)
# each simulator's episode length when --max-steps is not given: Push-T's and Lift's are the 300
# `sefa eval` always used; Meta-World's is its own max_path_length
DEFAULT_MAX_STEPS = {"pusht": 300, "robosuite:Lift": 300, METAWORLD: 500}
Log = Callable[[str], None]


def env_family(env: str) -> str:
    return METAWORLD if env.startswith(METAWORLD) else env


@dataclass(frozen=True)
class EvalRequest:
    """One `sefa eval`: closed-loop rollouts in `env`, or (env None) metrics on the store."""

    env: str | None = None
    n_test: int = 50
    start_seed: int = 100000
    max_steps: int | None = None  # None: the simulator's own (DEFAULT_MAX_STEPS)
    solver: str | None = None
    steps: int | None = None
    windows: int | None = None  # None: the checkpoint's training.val_sample_windows
    samples: int = 8
    # rollouts: the simulator's observation names -> the policy's keys (`--key-map NAME=KEY`)
    key_map: tuple[tuple[str, str], ...] = ()
    # rollouts: how chunks become actions (`--execution ...`); None: sefa.yaml's, else the one
    # chosen for each policy, else receding over n_action_steps (resolve_execution)
    execution: Any = None

    @property
    def mode(self) -> str:
        return self.env or "offline"

    @property
    def episode_steps(self) -> int:
        if self.max_steps is not None:
            return self.max_steps
        return DEFAULT_MAX_STEPS[env_family(self.env)] if self.env else 0

    def settings(self, execution=None, default: bool = True) -> dict[str, Any]:
        """What the result's cache key holds besides the checkpoint (`execution`: the resolved
        one a rollout runs; `default`: whether it is the field's, which earlier results ran
        and so keep their keys)."""
        if self.env is not None:
            out = {"n_test": self.n_test, "start_seed": self.start_seed,
                   "max_steps": self.episode_steps, "solver": self.solver, "steps": self.steps}
            if self.key_map:  # only when given: earlier results keep their keys
                out["key_map"] = dict(self.key_map)
            if execution is not None and not default:
                out["execution"] = execution.to_json()
            return out
        return {"windows": self.windows, "samples": self.samples, "solver": self.solver,
                "steps": self.steps}


def rollout_envs(obs_keys: Collection[str]) -> list[str]:
    """The simulators that give every observation a policy with these keys reads (what
    `sefa eval --env` can run it in): Push-T's own names (keypoint, state, img); Lift's and
    Meta-World's as `sefa collect` records them (`observation.` + the recorded key)."""
    from sefa_sim.collect import DEFAULT_CAMERAS, LOW_DIM_KEYS, OBJECT_KEY
    from sefa_sim.metaworld import OBS_KEYS as METAWORLD_KEYS
    from sefa_sim.pusht import LEROBOT_PUSHT_NAMES, OBS_KEYS

    keys = set(obs_keys)
    if keys == set(LEROBOT_PUSHT_NAMES.values()):  # LeRobot's Push-T: `sefa eval` maps them
        keys = set(LEROBOT_PUSHT_NAMES)
    lift = {f"observation.{k}" for k in (*LOW_DIM_KEYS, OBJECT_KEY[1],
                                         *(f"{c}_image" for c in DEFAULT_CAMERAS))}
    metaworld = {f"observation.{k}" for k in METAWORLD_KEYS}
    return [env for env, offered in (("pusht", set(OBS_KEYS)), ("robosuite:Lift", lift),
                                     (METAWORLD + "TASK", metaworld))
            if keys and keys <= offered]


def check_request(env: str | None, offline: bool, key_map: dict | None = None) -> str | None:
    """The environment as results name it (`metaworld:Reach-v3` is `metaworld:reach`), or a
    one-line error."""
    if env is None and not offline:
        raise SefaInputError("choose --offline (store-based metrics) or --env pusht (rollouts)")
    if key_map and env != "pusht":
        raise SefaInputError("--key-map maps Push-T's observation names (--env pusht); "
                             "robosuite:Lift's are `observation.` + robosuite's", key="--key-map")
    if env is not None and env.startswith(METAWORLD):
        from sefa_sim.metaworld import canonical

        return METAWORLD + canonical(env.removeprefix(METAWORLD))  # or one line naming them all
    if env is not None and env not in ENVS:
        raise SefaInputError(f"unknown environment '{env}' (available: {', '.join(ENVS)}, "
                             f"{METAWORLD}TASK or {METAWORLD}GROUP)", key="--env")
    return env


def default_checkpoints(workspace: Path) -> list[Path]:
    """The policies of the workspace's stage graph that have a checkpoint: the base flow, the
    last reflowed flow there is, the one-step policy."""
    from sefa_pipelines.stages import eval_defaults, stage_graph
    from sefa_pipelines.workspace import settings

    found = eval_defaults(stage_graph(settings(workspace, write=False)[0]), workspace)
    if not found:
        raise SefaInputError("no trained policy in this workspace (run `sefa train` first)",
                             file=str(workspace))
    return found


def evaluate(workspace: Path, checkpoints: list[Path], request: EvalRequest, *, device: str,
             force: bool, out: Path | None, is_main: bool, log: Log) -> list[dict[str, Any]]:
    """Evaluate each checkpoint (each result cached in WORKSPACE/evals/); the records, each
    marked `cached`. Under torchrun only rank 0's hold every record."""
    if out is not None and len(checkpoints) != 1:
        raise SefaInputError("--out takes one checkpoint", key="--out")
    records = []
    for c in checkpoints:
        execution, source, n = run_execution(workspace, c, request)
        run = _evaluation(workspace, c, request, execution, device, is_main, log)
        default = execution is None or execution.is_default(n)
        record, computed = cached_eval(workspace, c, request.mode,
                                       request.settings(execution, default), run, force=force,
                                       is_main=is_main)
        if record is None:
            continue
        how = "" if execution is None else f", {execution.label} ({source})"
        log(f"{label(workspace, c)}: {'evaluated' if computed else 'cached'} "
            f"({request.mode}{how}, {record_folder(workspace, record)}): {key_metric(record)}")
        if out is not None and request.env is not None and is_main:  # one writer under torchrun
            src = workspace / record_folder(workspace, record) / "eval_log.json"
            atomic.write_bytes(out / "eval_log.json", src.read_bytes())
        records.append(record | {"cached": not computed})
    return records


def run_execution(workspace: Path, checkpoint: Path, request: EvalRequest):
    """(the execution a rollout of this checkpoint runs, resolved; where it came from; the
    policy's n_action_steps), or (None, "", 0) for store metrics."""
    if request.env is None:
        return None, "", 0
    from sefa_model.policy.execution import resolve_execution
    from sefa_pipelines.workspace import settings

    yaml_execution = settings(workspace, write=False)[0].execution
    return resolve_execution(checkpoint, request.execution, request.solver, request.steps,
                             fallback=yaml_execution)


def weak_policy(workspace: Path, execution) -> tuple[str, str | None, int | None] | None:
    """bid's weaker policy (checkpoint, solver, steps), a relative checkpoint looked for in
    the workspace first."""
    if execution is None or execution.mode != "bid":
        return None
    from sefa_model.eval.latency import parse_target

    path, solver, steps = parse_target(execution.weak)
    if not Path(path).is_absolute() and (workspace / path).exists():
        path = str(workspace / path)
    return path, solver, steps


def _evaluation(workspace: Path, checkpoint: Path, request: EvalRequest, execution, device: str,
                is_main: bool, log: Log) -> Callable[[Path], dict[str, Any] | None]:
    r = request
    if r.env is None:
        from sefa_pipelines.stages import STORE
        from sefa_model.eval.offline import evaluate_offline

        def offline(folder: Path) -> dict[str, Any] | None:
            if not is_main:  # store metrics are one batched pass: rank 0 alone
                return None
            return evaluate_offline(checkpoint, workspace / STORE, windows=r.windows,
                                    samples=r.samples, solver=r.solver, steps=r.steps,
                                    device=device, log=log)
        return offline
    from sefa_sim.rollouts import evaluate_lift, evaluate_metaworld, evaluate_pusht

    if r.env.startswith(METAWORLD):
        from sefa_sim.metaworld import resolve

        run_env = partial(evaluate_metaworld, tasks=resolve(r.env.removeprefix(METAWORLD)),
                          env_name=r.env)
    else:
        run_env = (partial(evaluate_pusht, key_map=dict(r.key_map), log=log) if r.env == "pusht"
                   else evaluate_lift)

    def rollouts(folder: Path) -> dict[str, Any]:
        try:
            return run_env(checkpoint, n_test=r.n_test, start_seed=r.start_seed,
                           max_steps=r.episode_steps, solver=r.solver, steps=r.steps, out=folder,
                           device=device, execution=execution,
                           weak=weak_policy(workspace, execution))
        except ImportError as e:
            raise SefaInputError(f"the simulator for '{r.env}' is not installed ({e}); "
                                 "install sefa[sim]") from None
    return rollouts




def record_folder(workspace: Path, record: dict[str, Any]) -> str:
    """Where a result is kept, as the workspace names it (evals/<mode>-<key>)."""
    return label(workspace, eval_dir(workspace, record["mode"], record["key"]))


def result_rows(workspace: Path, records: list[dict[str, Any]], env: str | None
                ) -> list[dict[str, Any]]:
    """What `sefa eval` reports per checkpoint (and prints with --json): the result, where it
    is kept and whether it was cached; a rollout's without its per-seed list."""
    if env is None:
        return [r["result"] | {"cached_in": record_folder(workspace, r), "cached": r["cached"]}
                for r in records]
    return [{k: v for k, v in r["result"].items() if k != "per_seed"}
            | {"eval_log": record_folder(workspace, r) + "/eval_log.json",
               "cached_in": record_folder(workspace, r), "cached": r["cached"]}
            for r in records]
