"""The built-in default (`sefa demo`) and a built-in ROS example.

`run_demo`: scripted robosuite Lift demonstrations (no download) through the whole SeFA pipeline,
then the base and one-step policies side by side, in the simulator and offline.

`record_reach_bag`: a scripted two-joint reaching task recorded as a ROS 2 bag (MCAP): the path
our users' own data takes (topics at different rates, header stamps, a topic map, resampling to
one fps). The robot is a kinematic planar two-link arm whose joints track a velocity command from
a proportional controller towards a random target.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np

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


LIFT_EPISODES = 100


def run_demo(workspace: Path, log: Callable[[str], None] = print,
             on_step: Callable[[int, int, float], None] | None = None) -> dict:
    """The built-in default, every step cached: collect scripted Lift demos, ingest them, run the
    SeFA pipeline, then evaluate the base flow (RK45 and one Euler step) and the one-step SeFA
    policy in the simulator and on the validation windows."""
    from sefa_pipelines.stages import load_pipeline, run_stages, save_pipeline
    from sefa_sim.collect import collect_lift
    from sefa_sim.rollouts import evaluate_lift

    workspace.mkdir(parents=True, exist_ok=True)
    demos = workspace / "recordings" / "lift.hdf5"
    if not demos.exists():
        demos.parent.mkdir(parents=True, exist_ok=True)
        log(f"collecting {LIFT_EPISODES} scripted Lift demonstrations to {demos}")
        collect_lift(demos, LIFT_EPISODES, seed=0)
    store = workspace / "dataset.zarr"
    ingest([demos], store, IngestOptions(), log=log)
    if not (workspace / "sefa.yaml").exists():
        save_pipeline(workspace, demo_pipeline())
    run_stages(workspace, load_pipeline(workspace), log=log, on_step=on_step or (lambda *a: None))
    rows = []
    from sefa_pipelines.report import student_label
    from sefa_pipelines.runner import Workspace

    # the student named by what ran: SeFA only when its alignment replaced something
    student = student_label(Workspace(workspace).read_manifest("distill").get("summary", {}))
    for name, run, solver, steps in (("base flow, RK45", "train", "rk45", None),
                                     ("base flow, Euler-1", "train", "euler", 1),
                                     (student, "distill", None, None)):
        row = measure_policy(workspace / run, store, [(name, solver, steps)])["rows"][0]
        out = workspace / run / f"eval_lift_{solver or 'own'}"
        if (out / "eval_log.json").exists():
            import json

            sim = json.loads((out / "eval_log.json").read_text())
        else:
            log(f"evaluating {name} on 50 Lift seeds")
            sim = evaluate_lift(workspace / run, n_test=50, solver=solver, steps=steps, out=out)
        rows.append({**row, "success_rate": sim["test/success_rate"], "n_test": sim["n_test"]})
    summary = measure_policy(workspace / "train", store, [])
    summary["rows"] = rows
    return {"store": store_summary(store), "policy": summary}


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
