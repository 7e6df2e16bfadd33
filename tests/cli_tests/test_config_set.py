"""`sefa config set` writes only what the commands that read sefa.yaml accept, and changes only
the value it sets (issue 33), through the real `sefa` command (in-process, tests/cli_inprocess.py)
on a workspace whose store is the real Push-T low-dim data (../shared/data):

- a train config file that does not exist, an unknown device, a batch larger than the store's
  training windows, an observation key the store lacks, text that is not YAML: each one line
  naming the key, sefa.yaml byte for byte as it was, and `sefa status` still answering;
- a negative number is a value, not an option;
- comments, key order and a symlinked sefa.yaml are kept;
- `sefa status` answers in a read-only workspace (it used to fail saving its hash cache).
"""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

from cli_inprocess import run_cli
from convert_bad_inputs import SEFA_YAML, read_only


def sefa(ws: Path, *args) -> subprocess.CompletedProcess:
    return run_cli(*args, "-w", ws, cwd=ws.parent)


@pytest.fixture(scope="module")
def store(shared_data, tmp_path_factory) -> Path:
    ws = tmp_path_factory.mktemp("store")
    r = sefa(ws, "ingest", shared_data / "pusht_cchi_v7_replay.zarr", "--fps", "10",
             "--key", "keypoint", "--key", "state", "--key", "action")
    assert r.returncode == 0, r.stderr
    return ws / "dataset.zarr"


@pytest.fixture
def ws(store, tmp_path) -> Path:
    ws = tmp_path / "ws"
    ws.mkdir()
    (ws / "dataset.zarr").symlink_to(store)
    (ws / "sefa.yaml").write_text(SEFA_YAML)
    return ws


def one_error(r: subprocess.CompletedProcess, *fragments: str) -> str:
    assert r.returncode == 1, (r.stdout, r.stderr)
    assert "Traceback" not in r.stderr and "a bug in sefa" not in r.stderr, r.stderr
    errors = [l for l in r.stderr.splitlines() if l.startswith("error:")]
    assert len(errors) == 1, r.stderr
    for f in fragments:
        assert f in errors[0], errors[0]
    return errors[0]


REFUSED = [
    # (key, value, what the one line says): each is what the command reading it refuses
    ("train_config", "nope.yaml", "nope.yaml: train_config: file not found"),
    ("device", "tpu", "device: unknown device 'tpu'"),
    ("train.training.batch_size", "100000",
     "training.batch_size: 100000 is more than the 21697 training windows"),
    ("train.shape_meta.obs_keys", "[nope]", "shape_meta.obs_keys: observation key 'nope' is not "
                                            "in the store"),
    ("reflow.iters", "[1", "reflow.iters: '[1' is not a YAML value"),
    ("align.eps", "-1", "align.eps: -1 is too small"),  # a negative number is a value
    ("align.eps", "-0.5", "align.eps: -0.5 is too small"),
]


@pytest.mark.parametrize("key,value,says", REFUSED, ids=[f"{k}={v}" for k, v, _ in REFUSED])
def test_a_value_the_commands_refuse_is_not_written(ws, key, value, says):
    r = sefa(ws, "config", "set", key, value)
    one_error(r, says)
    assert (ws / "sefa.yaml").read_text() == SEFA_YAML
    assert not (ws / "sefa.yaml.bak").exists()
    r = sefa(ws, "status")
    assert r.returncode == 0, r.stderr


def test_only_the_value_changes_comments_and_symlink_kept(ws, tmp_path):
    real = tmp_path / "repo" / "sefa.yaml"  # a config kept elsewhere (a repository), linked
    real.parent.mkdir()
    shutil.move(ws / "sefa.yaml", real)
    (ws / "sefa.yaml").symlink_to(real)
    for key, value in [("reflow.iters", "3"), ("train.training.max_steps", "5"),
                       ("train.training.lr", "1e-3"), ("align.eps", "0.05")]:
        r = sefa(ws, "config", "set", key, value)
        assert r.returncode == 0, r.stderr
    assert os.path.islink(ws / "sefa.yaml") and os.readlink(ws / "sefa.yaml") == str(real)
    text = real.read_text()
    assert text == """\
# tuned by hand: keep these notes
train:  # the base policy
- policy.head=mlp  # small and quick
- policy.mlp_hidden_dims=[8,8]
- policy.time_embed_dim=8
- training.max_steps=5
- training.lr=1e-3
reflow:
  iters: 3   # two rounds
align:
  eps: 0.05
"""
    assert (ws / "sefa.yaml.bak").read_text() == text.replace("align:\n  eps: 0.05\n", "")
    r = sefa(ws, "config", "show")
    assert r.returncode == 0 and "iters: 3" in r.stdout and "eps: 0.05" in r.stdout


def test_status_answers_in_a_read_only_workspace(ws):
    r = run_cli("train", "-w", ws, cwd=ws.parent, threads=1)
    assert r.returncode == 0, r.stderr
    (ws / ".sefa" / "file_hashes.json").unlink(missing_ok=True)  # status would save it
    writable = sefa(ws, "status")
    (ws / ".sefa" / "file_hashes.json").unlink(missing_ok=True)
    try:
        if not read_only(ws, True):
            pytest.skip("running as root where chattr cannot make a folder read-only")
        r = sefa(ws, "status")
    finally:
        read_only(ws, False)
    assert r.returncode == 0, r.stderr
    assert r.stdout == writable.stdout and "train          cached" in r.stdout
