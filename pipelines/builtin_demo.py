"""The built-in default (`sefa demo`) and a built-in ROS example.

`run_demo`: scripted Meta-World demonstrations (no download) through the whole SeFA pipeline,
then the base flow (solved accurately, and in one Euler step) beside the one-step student, each
under the executions the project measures, in the simulator and offline.

`record_reach_bag`: a scripted two-joint reaching task recorded as a ROS 2 bag (MCAP): the path
our users' own data takes (topics at different rates, header stamps, a topic map, resampling to
one fps). The robot is a kinematic planar two-link arm whose joints track a velocity command from
a proportional controller towards a random target.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from sefa_data.errors import SefaInputError
from sefa_data.ingest import IngestOptions, ingest
from sefa_data.store.inspect import store_summary

JOINTS = ["shoulder_joint", "elbow_joint"]
STATE_HZ, COMMAND_HZ, TARGET_HZ = 100, 50, 10

TOPIC_MAP = f"""\
# Written by `sefa demo`: which topic becomes which dataset key.
fps: 10
stamp: header
features:
  observation.state:
    topic: /joint_states
    field: position[{', '.join(JOINTS)}]
  observation.target:
    topic: /target
    field: point
    resample: hold
  action:
    topic: /joint_commands
    field: velocity[{', '.join(JOINTS)}]
split:
  gap_s: 1.0
"""


def _stamp(typestore, ns: int):
    Time = typestore.types["builtin_interfaces/msg/Time"]
    return Time(sec=int(ns // 1_000_000_000), nanosec=int(ns % 1_000_000_000))


def record_reach_bag(path: Path, episodes: int = 6, seconds: float = 4.0, seed: int = 0) -> Path:
    """Write the scripted demonstrations as a ROS 2 bag directory with MCAP storage."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    rng = np.random.default_rng(seed)
    dt = 1.0 / STATE_HZ
    t_ns = 1_700_000_000 * 10**9
    with Writer(path, version=8, storage_plugin=StoragePlugin.MCAP) as w:
        c_state = w.add_connection("/joint_states", "sensor_msgs/msg/JointState", typestore=ts)
        c_cmd = w.add_connection("/joint_commands", "sensor_msgs/msg/JointState", typestore=ts)
        c_target = w.add_connection("/target", "geometry_msgs/msg/PointStamped", typestore=ts)

        def joint_msg(ns, pos, vel):
            header = T["std_msgs/msg/Header"](stamp=_stamp(ts, ns), frame_id="base")
            return T["sensor_msgs/msg/JointState"](
                header=header, name=JOINTS, position=np.asarray(pos, np.float64),
                velocity=np.asarray(vel, np.float64), effort=np.zeros(0, np.float64))

        for _ in range(episodes):
            q = rng.uniform(-1.0, 1.0, 2)
            goal = rng.uniform(-1.5, 1.5, 2)
            cmd = np.zeros(2)
            for step in range(int(seconds * STATE_HZ)):
                if step % (STATE_HZ // COMMAND_HZ) == 0:
                    cmd = np.clip(2.0 * (goal - q), -1.5, 1.5)  # the scripted expert
                    w.write(c_cmd, t_ns, ts.serialize_cdr(joint_msg(t_ns, q, cmd), c_cmd.msgtype))
                if step % (STATE_HZ // TARGET_HZ) == 0:
                    header = T["std_msgs/msg/Header"](stamp=_stamp(ts, t_ns), frame_id="base")
                    point = T["geometry_msgs/msg/Point"](x=float(goal[0]), y=float(goal[1]), z=0.0)
                    msg = T["geometry_msgs/msg/PointStamped"](header=header, point=point)
                    w.write(c_target, t_ns, ts.serialize_cdr(msg, c_target.msgtype))
                w.write(c_state, t_ns, ts.serialize_cdr(joint_msg(t_ns, q, np.zeros(2)), c_state.msgtype))
                q = q + cmd * dt
                t_ns += int(dt * 1e9)
            t_ns += 3 * 10**9  # the operator resets the scene: a silence the ingest splits on
    return path


# The demo's task and its size (docs/measurements.md, "Choosing the demo's task": the candidates
# measured and why this one). 10 demonstrations: Meta-World's few-demonstration setting.
DEMO_TASK = "button-press"
DEMO_EPISODES = 10
N_TEST = 50  # test seeds from 100000, as every Meta-World result of the project


@dataclass(frozen=True)
class DemoRow:
    """One row of the demo's table: a policy (its run, its sampler) under one execution."""
    name: str
    run: str  # train (the base flow) or distill (the one-step student)
    solver: str | None = None  # None: the checkpoint's own
    steps: int | None = None
    every: int | None = None  # a new prediction every `every` steps; None: n_action_steps


def demo_rows(student: str) -> tuple[DemoRow, ...]:
    """The base flow solved accurately (RK45) and in one Euler step, and the one-step student,
    each one-step policy at the field's execution (the chunk's n_action_steps actions per
    prediction) and predicting at every step (what one network call a step affords)."""
    return (DemoRow("base flow, RK45", "train", "rk45"),
            DemoRow("base flow, Euler-1", "train", "euler", 1),
            DemoRow("base flow, Euler-1", "train", "euler", 1, every=1),
            DemoRow(student, "distill"),
            DemoRow(student, "distill", every=1))


def run_demo(workspace: Path, log: Callable[[str], None] = print,
             on_step: Callable[[int, int, float], None] | None = None, *,
             task: str = DEMO_TASK, episodes: int = DEMO_EPISODES, n_test: int = N_TEST,
             pipeline=None) -> dict:
    """The built-in default, every step cached: scripted Meta-World demonstrations of `task`,
    ingested, through the SeFA pipeline (`pipeline`, default builtin_default.yaml), then each
    of `demo_rows` evaluated in the simulator on `n_test` seeds and on the validation windows."""
    from sefa_pipelines.report import student_label
    from sefa_pipelines.runner import Workspace
    from sefa_pipelines.stages import load_pipeline, run_stages, save_pipeline
    from sefa_sim.metaworld import collect_metaworld

    workspace.mkdir(parents=True, exist_ok=True)
    demos = workspace / "recordings" / f"{task}.hdf5"
    if (workspace / "sefa.yaml").exists() and not demos.exists():
        # a workspace of other data (an earlier sefa's Lift demo): its store takes no other keys
        raise SefaInputError(f"a workspace that is not this demo's (it has a sefa.yaml but no "
                             f"recordings/{task}.hdf5): remove it, or give the demo another "
                             "workspace with -w", file=str(workspace))
    if not demos.exists():
        demos.parent.mkdir(parents=True, exist_ok=True)
        log(f"collecting {episodes} scripted Meta-World {task} demonstrations to {demos}")
        collect_metaworld(demos, task, episodes, seed=0)
    store = workspace / "dataset.zarr"
    ingest([demos], store, IngestOptions(), log=log)
    if not (workspace / "sefa.yaml").exists():
        save_pipeline(workspace, pipeline or demo_pipeline())
    run_stages(workspace, load_pipeline(workspace), log=log, on_step=on_step or (lambda *a: None))
    # the student named by what ran: SeFA only when its alignment replaced something
    student = student_label(Workspace(workspace).read_manifest("distill").get("summary", {}))
    measured: dict[tuple, dict] = {}  # (run, solver, steps) -> its offline row
    rows = []
    for row in demo_rows(student):
        setting = (row.run, row.solver, row.steps)
        if setting not in measured:
            measured[setting] = measure_policy(workspace / row.run, store,
                                               [(row.name, row.solver, row.steps)])["rows"][0]
        sim = evaluate_row(workspace, row, task, n_test, log)
        rows.append({**measured[setting], "policy": row.name, "run": row.run,
                     "solver": sim["solver"], "execution": sim["execution_label"],
                     "every": sim["execution"]["replan_every"],
                     "success_rate": sim["test/success_rate"], "n_test": sim["n_test"],
                     # each seed's outcome: the student and one Euler step are compared paired
                     "per_seed": [[r["seed"], float(r["success"])] for r in sim["per_seed"]]})
    summary = measure_policy(workspace / "train", store, [])
    summary.update(rows=rows, env=f"Meta-World {task}", findings=findings(rows))
    return {"store": store_summary(store), "policy": summary}


def findings(rows: list[dict]) -> list[str]:
    """What the table shows, in words, from its numbers: the student against one Euler step of
    its base flow under each execution (the same cost: one network evaluation a prediction), and
    whether the accurate solve could predict at every control step."""
    from sefa_pipelines.comparison import paired_difference
    from sefa_sim.metaworld import CONTROL_FREQ

    def against(a: dict, b: dict) -> str:
        diff, se, _ = paired_difference({(None, k): v for k, v in a["per_seed"]},
                                        {(None, k): v for k, v in b["per_seed"]})
        spread = "" if se is None else f" ± {100 * se:.0f}"
        return (f"{a['success_rate']:.0%} against {b['success_rate']:.0%} "
                f"({100 * diff:+.0f}{spread} points)")

    def execution(every: int) -> str:
        return "predicting at every step" if every == 1 else f"with {every} actions a prediction"

    euler = {r["every"]: r for r in rows if r["run"] == "train" and r["solver"] == "euler-1"}
    student = [r for r in rows if r["run"] == "distill" and r["every"] in euler]
    out = []
    if student:
        out.append(f"The {student[0]['policy']} student against one Euler step of its base flow, "
                   "at the same cost (one network evaluation a prediction), paired over the same "
                   "seeds (± the standard error): "
                   + ", ".join(f"{against(r, euler[r['every']])} {execution(r['every'])}"
                               for r in student) + ".")
    period_ms = 1000 / CONTROL_FREQ
    rk45 = next((r for r in rows if r["run"] == "train" and r["solver"] == "rk45"), None)
    if rk45 is not None:
        fits = rk45["latency_ms"] <= period_ms
        out.append(f"The base flow solved accurately (RK45, {rk45['nfe']} network evaluations) "
                   f"succeeds in {rk45['success_rate']:.0%} at {rk45['latency_ms']:.0f} ms a "
                   f"prediction: {'fast enough' if fits else 'too slow'} to predict at every "
                   f"step of Meta-World's {period_ms:.1f} ms control period.")
    return out


def evaluate_row(workspace: Path, row: DemoRow, task: str, n_test: int,
                 log: Callable[[str], None]) -> dict:
    """The row's success rate in the simulator, cached in the workspace as `sefa eval --env
    metaworld:TASK` caches it (so `sefa results` lists it too): its eval log."""
    import json

    from sefa_model.policy.execution import ExecutionSettings
    from sefa_pipelines.evals import METAWORLD, EvalRequest, evaluate, record_folder

    execution = None if row.every is None else ExecutionSettings("receding", row.every)
    log(f"{row.name}, " + ("a prediction every step" if row.every == 1 else
                           "the chunk's actions a prediction")
        + f": {n_test} test seeds of Meta-World {task}")
    request = EvalRequest(env=METAWORLD + task, n_test=n_test, solver=row.solver,
                          steps=row.steps, execution=execution)
    [record] = evaluate(workspace, [workspace / row.run], request, device="auto", force=False,
                        out=None, is_main=True, log=log)
    return json.loads((workspace / record_folder(workspace, record) / "eval_log.json").read_text())


def demo_pipeline():
    """The built-in default's settings (pipelines/builtin_default.yaml)."""
    from sefa_pipelines.stages import PipelineConfig
    from sefa_data.config_io import from_dict, load_yaml

    path = Path(__file__).with_name("builtin_default.yaml")
    cfg = from_dict(PipelineConfig, load_yaml(path), source=str(path))
    cfg.train_config = str(path.with_name(cfg.train_config))  # shipped beside it
    return cfg


def measure_policy(run: Path, store: Path, settings: list[tuple[str, str | None, int | None]]) -> dict:
    """Validation action MSE, NFE and batch-1 latency of a checkpoint with each solver setting
    (None: the checkpoint's own)."""
    import numpy as np
    import torch

    from sefa_data.sampler import SequenceSampler
    from sefa_data.store.zarr_store import EpisodeStore
    from sefa_model.eval.latency import time_calls
    from sefa_model.policy.artifact import Policy

    policy = Policy.load(run)
    p = policy.cfg.policy
    sampler = SequenceSampler(EpisodeStore.open(store), p.horizon, p.n_obs_steps, p.n_action_steps,
                              split="valid", obs_keys=list(policy.cfg.shape_meta.obs))
    batch = sampler.batch(np.arange(len(sampler)))
    key = policy.cfg.shape_meta.action.key
    obs = {k: batch[k] for k in policy.cfg.shape_meta.obs}
    noise = torch.randn(len(sampler), p.horizon, batch[key].shape[-1],
                        generator=torch.Generator().manual_seed(0))
    rows = []
    for name, solver, steps in settings:
        pred = policy.predict_action(obs, solver=solver, steps=steps, noise=noise)
        mse = float(np.mean((pred.action_pred.numpy() - batch[key]) ** 2))
        one = {k: v[:1] for k, v in obs.items()}
        times = time_calls({"predict": lambda: policy.predict_action(one, solver=solver, steps=steps)},
                           warmup=1, calls=20, max_seconds=float("inf"), sync=lambda: None)["predict"]
        rows.append({"policy": name, "val_action_mse": mse, "nfe": pred.nfe,
                     "latency_ms": 1e3 * float(np.median(times))})
    mean_mse = float(np.mean((batch[key].mean(axis=(0, 1)) - batch[key]) ** 2))
    return {"checkpoint": policy.path, "val_windows": len(sampler), "rows": rows,
            "mean_action_mse": mean_mse}
