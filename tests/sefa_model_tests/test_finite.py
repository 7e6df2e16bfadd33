"""Finite or nothing (issue 23): checkpoints carry checksums that every reader checks, nothing
non-finite is written, loaded, exported or evaluated, and a diverging training stops with one
line and publishes nothing.

The damaged checkpoints are copies of the deployment tests' tiny Push-T checkpoints
(tests/deploy_helpers.py) edited in place: a flipped exponent bit, a NaN written with
safetensors' own writer, an edited config.json.
"""

from __future__ import annotations

import json
import shutil
import struct
import subprocess
import threading
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file, save_file

from cli_inprocess import run_cli
from sefa_data.errors import NonFiniteError, SefaInputError
from sefa_model.policy.checkpoint import (CHECKSUMS_FILE, open_checkpoint, write_checksums,
                                   write_checkpoint)
from sefa_model.policy.artifact import Policy

REPO = Path(__file__).resolve().parents[2]
TINY = ["shape_meta.obs.keypoint.type=low_dim", "shape_meta.obs.state.dims=[0,2]",
        "policy.head=mlp", "policy.mlp_hidden_dims=[32,32]", "policy.time_embed_dim=16",
        "training.max_steps=40", "training.batch_size=32", "training.lr_warmup_steps=0",
        "training.val_every=20", "training.checkpoint_every=20", "training.val_batches=1",
        "training.val_sample_windows=8", "training.log_every=10"]


@pytest.fixture
def ckpt(deploy_workspace, tmp_path) -> Path:
    """A private copy of the one-step student's checkpoint."""
    out = tmp_path / "ckpt"
    shutil.copytree(deploy_workspace / "distill" / "checkpoints" / "latest", out)
    return out


def flip_exponent_bit(path: Path) -> None:
    """Flip the top exponent bit of the first value of a safetensors file (float32: 0.01
    becomes about 3e36, still finite, which only the checksum can tell; 1.5 becomes Inf)."""
    data = bytearray(path.read_bytes())
    header = struct.unpack("<Q", data[:8])[0]
    data[8 + header + 3] ^= 0x40
    path.write_bytes(bytes(data))


def sefa(*args, cwd=REPO) -> subprocess.CompletedProcess:
    """`sefa ARGS` in-process through sefa_cli.main.main (tests/cli_inprocess.py); the artifacts
    catalogue (tests/artifact_bad_inputs.py) runs the same refusals in real child processes."""
    return run_cli(*args, cwd=cwd)


def one_error_line(r: subprocess.CompletedProcess) -> str:
    assert r.returncode == 1, (r.returncode, r.stderr[-2000:])
    assert "Traceback" not in r.stderr, r.stderr
    errors = [line for line in r.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1, r.stderr
    return errors[0]


# what reads each file: a policy to run (its EMA weights, or the raw ones when asked), and a run
# to continue or start from (open_checkpoint: every file, the optimizer state included)
READERS = {"ema.safetensors": lambda c: Policy.load(c),
           "normalizer.safetensors": lambda c: Policy.load(c),
           "model.safetensors": lambda c: Policy.load(c, ema=False),
           "training_state/state.safetensors": open_checkpoint}


@pytest.mark.parametrize("name", list(READERS))
def test_a_flipped_bit_in_any_tensor_file_is_a_checksum_error(ckpt, name):
    before = {k: v.clone() for k, v in load_file(str(ckpt / name)).items()}
    flip_exponent_bit(ckpt / name)
    after = load_file(str(ckpt / name))
    assert any(not torch.equal(before[k], after[k]) for k in before)  # really damaged
    with pytest.raises(SefaInputError, match=rf"{name}: checksum mismatch .* damaged"):
        READERS[name](ckpt)
    with pytest.raises(SefaInputError, match=rf"{name}: checksum mismatch .* damaged"):
        open_checkpoint(ckpt)


def test_edited_json_files_and_added_or_missing_files_are_named(ckpt):
    config = ckpt / "config.json"
    config.write_text(config.read_text().replace('"horizon": 16', '"horizon": 8'))
    with pytest.raises(SefaInputError, match=r"config.json: checksum mismatch"):
        Policy.load(ckpt)
    write_checksums(ckpt)
    (ckpt / "extra.safetensors").write_bytes(b"x")
    with pytest.raises(SefaInputError, match=r"extra.safetensors: a file not recorded"):
        open_checkpoint(ckpt)  # the whole check, as a resumed or continued run gets it
    (ckpt / "extra.safetensors").unlink()
    (ckpt / "processor.json").unlink()
    with pytest.raises(SefaInputError, match=r"processor.json: missing checkpoint file"):
        Policy.load(ckpt)


def test_checkpoints_without_checksums_still_load_and_their_weights_are_checked(ckpt):
    (ckpt / CHECKSUMS_FILE).unlink()  # as written before checksums existed
    Policy.load(ckpt)
    weights = load_file(str(ckpt / "ema.safetensors"))
    name = sorted(weights)[0]
    weights[name].view(-1)[0] = float("nan")
    save_file(weights, str(ckpt / "ema.safetensors"))
    with pytest.raises(NonFiniteError, match=rf"ema.safetensors: non-finite weights.*{name} has 1 of"):
        Policy.load(ckpt)


def test_missing_ema_weights_are_an_error_unless_the_raw_weights_are_asked_for(ckpt):
    (ckpt / "ema.safetensors").unlink()
    write_checksums(ckpt)
    with pytest.raises(SefaInputError, match=r"ema.safetensors: missing checkpoint file: the run "
                                             r"kept EMA weights"):
        Policy.load(ckpt)
    assert Policy.load(ckpt, ema=False).weights == "model.safetensors"


def test_export_says_which_weights_it_holds(ckpt, tmp_path):
    (ckpt / "ema.safetensors").unlink()
    write_checksums(ckpt)
    assert "missing checkpoint file" in one_error_line(
        sefa("export", ckpt, "--out", tmp_path / "a", "--format", "torchscript", "--fps", "10"))
    r = sefa("export", ckpt, "--out", tmp_path / "b", "--format", "torchscript", "--fps", "10",
             "--raw-weights")
    assert r.returncode == 0, r.stderr
    assert json.loads((tmp_path / "b" / "metadata.json").read_text())["weights"] == "model.safetensors"


@pytest.mark.parametrize("edit,message", [
    (lambda c: c.update(kind="banana"), r"kind: unknown kind 'banana'"),
    (lambda c: c.update(checkpoint_format=99), r"checkpoint_format: checkpoint_format 99 is not one"),
    (lambda c: c["train_config"].pop("policy"), r"train_config.policy: train_config lacks 'policy'"),
])
def test_config_json_must_be_one_sefa_wrote(ckpt, edit, message):
    config = json.loads((ckpt / "config.json").read_text())
    edit(config)
    (ckpt / "config.json").write_text(json.dumps(config))
    write_checksums(ckpt)  # consistent checksums: the config's own checks must catch it
    with pytest.raises(SefaInputError, match=message):
        Policy.load(ckpt)


def test_non_finite_weights_are_never_written(ckpt, tmp_path):
    policy = Policy.load(ckpt)
    with torch.no_grad():
        next(policy.model.parameters()).view(-1)[0] = float("inf")
    out = tmp_path / "out"
    with pytest.raises(NonFiniteError, match=r"model.safetensors: refusing to write non-finite"):
        write_checkpoint(out, config={}, model=policy.model, ema=None,
                         normalizer=policy.normalizer, training_state=None)
    assert not out.exists() and not list(tmp_path.glob(".out*"))


def overflowing(ckpt: Path) -> None:
    """Finite weights whose outputs are not: the head's last layer scaled to overflow float32
    (checksums rewritten, as a training that wrote them would have)."""
    for name in ("ema.safetensors", "model.safetensors"):
        weights = load_file(str(ckpt / name))
        for key in weights:
            if key.endswith("weight") and weights[key].is_floating_point():
                weights[key] = weights[key] * 1e30
        save_file(weights, str(ckpt / name))
    write_checksums(ckpt)


def test_export_refuses_a_policy_whose_outputs_are_not_finite(ckpt, tmp_path):
    pytest.importorskip("onnxruntime")
    overflowing(ckpt)
    for fmt in ("torchscript", "onnx"):
        r = sefa("export", ckpt, "--out", tmp_path / fmt, "--format", fmt, "--fps", "10")
        line = one_error_line(r)
        assert "outputs NaN or Inf on random inputs" in line and "nothing is published" in line
        assert not (tmp_path / fmt).exists() and not list(tmp_path.glob(f".{fmt}*"))


def test_export_checks_its_artifact_on_a_real_window(deploy_workspace, tmp_path):
    out = tmp_path / "ts"
    r = sefa("export", deploy_workspace / "distill", "--out", out, "--format", "torchscript")
    assert r.returncode == 0, r.stderr
    assert "checked the artifact on a window of " in r.stderr and "dataset.zarr: finite" in r.stderr
    assert (out / "policy.pt").exists()


def test_offline_eval_refuses_non_finite_actions(ckpt, deploy_workspace):
    from sefa_model.eval.offline import evaluate_offline

    overflowing(ckpt)
    with pytest.raises(NonFiniteError, match=r"actions are NaN or Inf for \d+ of \d+ sampled "
                                             r"chunks .*no evaluation is recorded"):
        evaluate_offline(ckpt, deploy_workspace / "dataset.zarr", windows=4, samples=2,
                         device="cpu")


def test_a_diverging_training_stops_with_one_line_and_publishes_nothing(deploy_workspace, tmp_path):
    ws = tmp_path / "ws"
    ws.mkdir()
    shutil.copytree(deploy_workspace / "dataset.zarr", ws / "dataset.zarr")
    r = sefa("train", "-w", ws, *TINY, "training.lr=1e8")
    line = one_error_line(r)
    assert "training diverged at step 10 of 40: the training loss is nan" in line
    assert "nothing from this run is published" in line and "training.lr" in line
    assert not (ws / "train").exists()
    assert not list((ws / "runs").glob("train/*")) and not list((ws / "runs").glob("train/.*"))
    # TensorBoard's event writer was stopped before its folder went: left running, its thread
    # flushed into the removed folder and printed a traceback (seen once in CI)
    from tensorboard.summary.writer.event_file_writer import _AsyncWriterThread

    assert not [t for t in threading.enumerate() if isinstance(t, _AsyncWriterThread)]
