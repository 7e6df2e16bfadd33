"""The plugin's tests run in LeRobot's own environment (Python >= 3.12, LeRobot 0.6.x) with sefa and
this plugin installed: scripts/lerobot_plugin_check.sh builds it and runs them. Their policies
are sefa's deployment tests' tiny ones (tests/deploy_helpers.py: seconds of training on the real
Push-T store in ../shared/data; skipped without it), exported with `sefa export --format
lerobot`: only plumbing is scored, never skill."""

from __future__ import annotations

import socket
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[3]
SHARED_DATA = REPO.parent / "shared" / "data"
HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(REPO / "tests"), str(HERE)]  # deploy_helpers; sefa_test_robot

# a policy that reads the robot state alone (what a LeRobot robot passes): Push-T's agent position
STATE_ONLY = ["shape_meta.obs_keys=[state]", "shape_meta.obs.state.dims=[0,2]", "policy.head=mlp",
              "policy.mlp_hidden_dims=[32,32]", "policy.time_embed_dim=16",
              "training.batch_size=32", "training.max_steps=4", "training.val_every=4",
              "training.val_sample_windows=4", "training.val_batches=1"]


@pytest.fixture(scope="session")
def exports(tmp_path_factory) -> dict[str, Path]:
    """{"pusht": the one-step student of Push-T's keypoints and agent position, receding
    horizon; "state": a flow reading the agent position alone, Euler-2, noise_seed 0}."""
    if not (SHARED_DATA / "pusht_cchi_v7_replay.zarr").is_dir():
        pytest.skip(f"the real Push-T store is not at {SHARED_DATA} (a clone without ../shared)")
    from deploy_helpers import make_checkpoints

    from sefa_model.config import load_train_config
    from sefa_model.train.loop import train
    from sefa_pipelines.lerobot_names import export_for_lerobot

    ws = make_checkpoints(SHARED_DATA, tmp_path_factory.mktemp("sefa"))
    train(load_train_config(None, STATE_ONLY), ws / "state", ws / "dataset.zarr")
    out = {"pusht": ws / "lerobot_pusht", "state": ws / "lerobot_state"}
    export_for_lerobot(ws / "distill", out["pusht"], key_map=None)
    export_for_lerobot(ws / "state", out["state"], key_map=None, solver="euler", steps=2)
    _set(out["state"], noise_seed=0)
    out["workspace"] = ws
    return out


def _set(folder: Path, **fields) -> None:
    """Change top-level fields of an export's config.json (what LeRobot's --policy.X does)."""
    import json

    path = folder / "config.json"
    config = json.loads(path.read_text())
    config.update(fields)
    path.write_text(json.dumps(config, indent=2))


@pytest.fixture
def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]
