"""LeRobot's own programs, unmodified, running sefa exports: `lerobot-eval` on gym-pusht,
`lerobot-rollout` on a robot without hardware (tests/sefa_test_robot.py), and the async
`policy_server` (through the plugin's launcher) with LeRobot's `robot_client` over loopback.
Each runs as its own process, as a user runs it."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

BIN = Path(sys.executable).parent
HERE = Path(__file__).resolve().parent
# the test robot's module on the path of the tools' processes; one torch thread each
ENV = {**os.environ, "PYTHONPATH": os.pathsep.join([str(HERE), os.environ.get("PYTHONPATH", "")]),
       "OMP_NUM_THREADS": "1", "HF_HUB_OFFLINE": "1"}


def run(cmd: list[str], cwd: Path, timeout: float = 600, **env) -> subprocess.CompletedProcess:
    """`cmd` in `cwd` (LeRobot's tools write logs/ and outputs/ into the working directory)."""
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, cwd=cwd,
                          env={**ENV, **env})
    assert done.returncode == 0, f"{cmd[0]} exited {done.returncode}:\n{done.stderr[-3000:]}"
    return done


def robot_log(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()] if path.exists() else []


def test_lerobot_eval_runs_the_pusht_export(exports, tmp_path):
    """lerobot-eval on LeRobot's keypoint Push-T (gym-pusht's 8 corners, mapped to the store's
    9 keypoints by the export): it runs, reports avg_max_reward and pc_success, and the
    rewards it saw are gym-pusht's (in [0, 1])."""
    out = tmp_path / "eval"
    done = run([str(BIN / "lerobot-eval"), f"--policy.path={exports['pusht']}", "--env.type=pusht",
         "--env.obs_type=environment_state_agent_pos", "--env.episode_length=40",
         "--eval.n_episodes=2", "--eval.batch_size=1", f"--output_dir={out}"], tmp_path)
    info = json.loads((out / "eval_info.json").read_text())
    overall = info["overall"]
    assert overall["n_episodes"] == 2
    assert 0.0 <= overall["avg_max_reward"] <= 1.0 and 0.0 <= overall["pc_success"] <= 100.0
    assert "Imported third-party plugin: lerobot_policy_sefa" in done.stdout + done.stderr


def replay(folder: Path, observations: list[dict]) -> np.ndarray:
    """The actions a fresh policy gives for these robot observations, one control step each."""
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.policies.factory import get_policy_class

    import lerobot_policy_sefa  # noqa: F401

    cfg = PreTrainedConfig.from_pretrained(folder)
    policy = get_policy_class("sefa").from_pretrained(folder, config=cfg)
    policy.reset()
    return np.stack([policy.select_action({"observation.state": torch.tensor(
        [[o["x.pos"], o["y.pos"]]], dtype=torch.float32)})[0].numpy() for o in observations])


def test_lerobot_rollout_drives_a_robot_with_the_policys_actions(exports, tmp_path):
    """lerobot-rollout (base strategy, sync inference) for 2 s at 10 fps: the robot receives
    the actions the policy gives for the observations it sent, step by step."""
    log = tmp_path / "robot.jsonl"
    run([str(BIN / "lerobot-rollout"), f"--policy.path={exports['state']}",
         "--robot.discover_packages_path=sefa_test_robot", "--robot.type=sefa_test_robot",
         "--fps=10", "--duration=2", "--return_to_initial_position=false",
         "--play_sounds=false", "--device=cpu"], tmp_path, SEFA_TEST_ROBOT_LOG=str(log))
    entries = robot_log(log)
    pairs, last = [], None
    for e in entries:
        if "observation" in e:
            last = e["observation"]
        elif last is not None:
            pairs.append((last, e["action"]))
    assert len(pairs) >= 10, entries[:5]
    want = replay(exports["state"], [o for o, _ in pairs])
    got = np.array([[a["x.pos"], a["y.pos"]] for _, a in pairs])
    np.testing.assert_allclose(got, want, atol=1e-3)


def test_async_robot_client_receives_actions_from_the_policy_server(exports, tmp_path, free_port):
    """LeRobot's policy_server, started by the plugin's launcher, serves the sefa export to
    LeRobot's robot_client over loopback; the first action the robot receives is the first of
    the chunk the policy predicts from the first observation it sent."""
    log = tmp_path / "robot.jsonl"
    server = subprocess.Popen(
        [sys.executable, "-m", "lerobot_policy_sefa.policy_server", "--host=127.0.0.1",
         f"--port={free_port}", "--fps=10"], env=ENV, cwd=tmp_path, stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT, text=True)
    client = None
    try:
        time.sleep(3)
        assert server.poll() is None, server.stdout.read()
        code = ("import sefa_test_robot, runpy, sys; sys.argv[0] = 'robot_client'; "
                "runpy.run_module('lerobot.async_inference.robot_client', run_name='__main__')")
        client = subprocess.Popen(
            [sys.executable, "-c", code, "--robot.type=sefa_test_robot", "--policy_type=sefa",
             f"--pretrained_name_or_path={exports['state']}", "--policy_device=cpu",
             f"--server_address=127.0.0.1:{free_port}", "--actions_per_chunk=8", "--fps=10"],
            env={**ENV, "SEFA_TEST_ROBOT_LOG": str(log)}, cwd=tmp_path, stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT, text=True)
        deadline = time.monotonic() + 180
        while sum("action" in e for e in robot_log(log)) < 10 and time.monotonic() < deadline:
            assert client.poll() is None, client.stdout.read()[-3000:]
            time.sleep(0.5)
    finally:
        for proc in (client, server):
            if proc is not None and proc.poll() is None:
                proc.send_signal(signal.SIGINT)
        for proc in (client, server):
            if proc is not None:
                try:
                    proc.wait(timeout=30)
                except subprocess.TimeoutExpired:
                    proc.kill()
    entries = robot_log(log)
    actions = [e["action"] for e in entries if "action" in e]
    assert len(actions) >= 10, (server.stdout.read() if server.stdout else "")[-3000:]
    first_obs = next(e["observation"] for e in entries if "observation" in e)
    want = replay(exports["state"], [first_obs])[0]
    np.testing.assert_allclose([actions[0]["x.pos"], actions[0]["y.pos"]], want, atol=1e-3)
