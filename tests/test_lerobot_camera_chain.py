"""The README's LeRobot Push-T (../shared/data/lerobot_pusht_v30: 206 episodes, a 96x96 AV1
camera `observation.image`, `observation.state` the agent's position) through the whole chain
with the real `sefa` command (in-process, tests/cli_inprocess.py) and the CPU preset
(`--preset lerobot_camera_cpu`: pipelines/lerobot_camera_cpu_train.yaml) at tiny lengths: ingest -> train -> reflow -> align ->
distill -> `sefa eval --env pusht` (LeRobot's names fed by the simulator) -> ONNX export."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from cli_inprocess import run_cli

REPO = Path(__file__).resolve().parents[1]
TINY = ["training.max_steps=4", "training.batch_size=8", "training.val_every=4",
        "training.checkpoint_every=4", "training.val_sample_windows=4", "training.val_batches=1",
        "training.lr_warmup_steps=1", "flow.solver=euler", "flow.steps=2"]


def sefa(ws: Path, *args):
    r = run_cli(*args, "-w", ws, cwd=REPO)
    assert r.returncode == 0, r.stderr[-3000:]
    return r


def test_lerobot_push_t_from_ingest_to_an_onnx_export(shared_data, tmp_path):
    pytest.importorskip("gym_pusht", reason="gym-pusht (the sim extra) is not installed")
    dataset = shared_data / "lerobot_pusht_v30"
    if not dataset.is_dir():
        pytest.skip(f"{dataset} not found")
    ws = tmp_path / "ws"
    sefa(ws, "ingest", dataset)
    r = sefa(ws, "train", "--preset", "lerobot_camera_cpu", *TINY)
    assert ("observations (2): observation.image (96, 96, 3) rgb resized to 64x64" in r.stderr
            and "observation.state (2,)" in r.stderr), r.stderr
    assert "cost: 4 steps of batch 8, about" in r.stderr, r.stderr  # said before the first step
    sefa(ws, "reflow", "--max-windows", "16", "--samples", "2", "--block-windows", "8")
    # a 4-step base flow: --eps auto stops (its samples are farther from the expert than the
    # mean action); the eps it named, given as a number, aligns the nearest 20 % anyway
    r = run_cli("align", "--eps", "auto", "-w", ws, cwd=REPO)
    assert r.returncode == 1 and "the base flow is not trained enough" in r.stderr, r.stderr
    eps = re.search(r"the nearest 20% of the couplings lie up to (\S+) from", r.stderr).group(1)
    sefa(ws, "align", "--eps", eps)
    sefa(ws, "distill", "--train-steps", "4")
    r = sefa(ws, "eval", "distill", "--env", "pusht", "--n-test", "1", "--max-steps", "8")
    assert "Push-T's img as observation.image, agent_pos as observation.state" in r.stderr
    (log,) = ws.glob("evals/pusht-*/eval_log.json")
    log = json.loads(log.read_text())
    assert log["n_test"] == 1 and 0 <= log["test/mean_score"] <= 1
    assert log["key_map"] == {"img": "observation.image", "agent_pos": "observation.state"}
    r = sefa(ws, "export", "distill", "--out", tmp_path / "onnx", "--json")
    meta = json.loads(r.stdout)
    assert meta["inputs"] == ["observation.image", "observation.state", "noise"]
    assert meta["obs"]["observation.image"]["shape"] == [2, 96, 96, 3]
    steps = json.loads((ws / "distill/checkpoints/latest/processor.json").read_text())
    assert {"resize": [64, 64], "interpolation": "bilinear, antialiased"} in \
        steps["obs"]["observation.image"]["steps"]
