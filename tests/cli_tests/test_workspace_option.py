"""`-w` is honoured by `sefa eval`, `sefa export` and `sefa serve`: a checkpoint named relative
(`train`, `distill`) is the workspace's, from whatever directory the command runs in."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from cli_inprocess import run_cli

REPO = Path(__file__).resolve().parents[2]
TINY = ["shape_meta.obs.keypoint.type=low_dim", "shape_meta.obs.state.dims=[0,2]",
        "policy.head=mlp", "policy.mlp_hidden_dims=[32,32]", "policy.time_embed_dim=16",
        "training.max_steps=10", "training.batch_size=32", "training.lr_warmup_steps=2",
        "training.val_every=10", "training.checkpoint_every=10", "training.val_batches=1",
        "training.val_sample_windows=8", "training.log_every=5"]


def sefa(cwd: Path, *args) -> subprocess.CompletedProcess:
    """`sefa ARGS` run from cwd, in-process through sefa_cli.main.main (tests/cli_inprocess.py),
    with the one torch thread its children had."""
    return run_cli(*args, cwd=cwd, threads=1)


def sefa_child(cwd: Path, *args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "sefa_cli.main", *map(str, args)], cwd=cwd,
                          capture_output=True, text=True, timeout=600,
                          env={**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"})


@pytest.fixture(scope="module")
def trained(shared_data, tmp_path_factory) -> Path:
    ws = tmp_path_factory.mktemp("wsopt") / "ws"
    for args in (["ingest", shared_data / "pusht_cchi_v7_replay.zarr", "--fps", "10", "--key",
                  "keypoint", "--key", "state", "--key", "action"], ["train", *TINY]):
        r = sefa(REPO, *args, "-w", ws)
        assert r.returncode == 0, r.stderr[-2000:]
    return ws


@pytest.fixture
def elsewhere(tmp_path) -> Path:
    """A directory with nothing of the workspace in it."""
    d = tmp_path / "elsewhere"
    d.mkdir()
    return d


def test_eval_reads_a_named_checkpoint_in_the_workspace(trained, elsewhere):
    r = sefa(elsewhere, "eval", "train", "--offline", "--windows", "8", "--samples", "2",
             "--json", "-w", trained)
    assert r.returncode == 0, r.stderr[-2000:]
    (row,) = json.loads(r.stdout)
    assert row["checkpoint"] == "train/checkpoints/latest"


def test_export_reads_a_named_checkpoint_in_the_workspace(trained, elsewhere):
    r = sefa(elsewhere, "export", "train", "-o", "out", "--format", "torchscript", "--solver",
             "euler", "--steps", "2", "-w", trained)
    assert r.returncode == 0, r.stderr[-2000:]
    assert (elsewhere / "out" / "policy.pt").exists()  # --out stays relative to where one is


def test_a_missing_checkpoint_is_named_where_it_was_looked_for(trained, elsewhere):
    for command in (["export", "distill", "-o", "out"], ["eval", "distill", "--offline"],
                    ["serve", "distill", "--port", "0"]):
        # serve in a child: a server that started by mistake would block this process
        run = sefa_child if command[0] == "serve" else sefa
        r = run(elsewhere, *command, "-w", trained)
        assert r.returncode == 1, r.stderr[-2000:]
        last = r.stderr.strip().splitlines()[-1]
        assert last == f"error: {trained / 'distill'}: no such checkpoint"
