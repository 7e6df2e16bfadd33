"""`sefa train` on the real Push-T demonstrations (low-dim: keypoints + agent position, as
Diffusion Policy's Push-T low-dim task), resume, checkpoints and the policy object (issue 3)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

from sefa_data.errors import SefaInputError
from sefa_data.ingest import IngestOptions, ingest
from sefa_model.config import load_train_config
from sefa_model.policy.artifact import Policy
from sefa_model.train.loop import Callbacks, train

REPO = Path(__file__).resolve().parents[2]

PUSHT_LOWDIM = [
    "shape_meta.obs.keypoint.type=low_dim",
    "shape_meta.obs.state.dims=[0,2]",  # the agent position, as DP's Push-T low-dim task
    "policy.head=mlp", "policy.mlp_hidden_dims=[256,256,256]", "policy.time_embed_dim=64",
    "training.batch_size=256", "training.lr=1e-3", "training.lr_warmup_steps=50",
    "training.val_batches=2", "training.val_sample_windows=128", "training.log_every=25",
]


@pytest.fixture(scope="module")
def pusht_store(shared_data, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("pusht") / "pusht.zarr"
    ingest([shared_data / "pusht_cchi_v7_replay.zarr"], out,
           IngestOptions(fps=10, keys=["keypoint", "state", "action"]))
    return out


@pytest.fixture(scope="module")
def trained(pusht_store, tmp_path_factory) -> Path:
    run = tmp_path_factory.mktemp("run") / "train"
    cfg = load_train_config(None, PUSHT_LOWDIM + ["training.max_steps=600", "training.val_every=300",
                                                  "training.checkpoint_every=300"])
    train(cfg, run, pusht_store)
    return run


def records(run: Path) -> list[dict]:
    return [json.loads(line) for line in (run / "logs.jsonl").read_text().splitlines()]


def test_pusht_loss_falls_and_val_mse_beats_the_mean_action(trained):
    logs = records(trained)
    losses = [r["train_loss"] for r in logs if "train_loss" in r]
    assert np.mean(losses[-4:]) < 0.5 * np.mean(losses[:2]), losses
    final = [r for r in logs if "val_action_mse" in r][-1]
    assert final["step"] == 600
    # in action units (pixels^2): the flow must do clearly better than the mean action
    assert final["val_action_mse"] < 0.5 * final["val_mean_action_mse"], final
    assert {"step", "epoch", "lr", "val_loss"} <= set(final)


def test_checkpoint_layout_and_flow_convention(trained):
    ckpt = trained / "checkpoints" / "latest"
    cfg = json.loads((ckpt / "config.json").read_text())
    assert cfg["flow_convention"]["x_t"] == "t * x1 + (1 - t) * x0"
    assert cfg["flow_convention"]["network_time"] == "t * 999"
    assert cfg["train_config"]["shape_meta"]["obs"]["keypoint"]["shape"] == [18]
    assert cfg["train_config"]["shape_meta"]["obs"]["state"]["shape"] == [2]
    for f in ("model.safetensors", "ema.safetensors", "normalizer.safetensors", "normalizer.json",
              "training_state/state.safetensors", "training_state/state.json"):
        assert (ckpt / f).is_file(), f
    assert (trained / "checkpoints" / "best" / "config.json").is_file()


def test_policy_predicts_and_euler100_agrees_with_rk45(trained, pusht_store):
    from sefa_data.sampler import SequenceSampler
    from sefa_data.store.zarr_store import EpisodeStore

    policy = Policy.load(trained)
    sampler = SequenceSampler(EpisodeStore.open(pusht_store), 16, 2, 8, split="valid",
                              obs_keys=["keypoint", "state"])
    batch = sampler.batch(np.arange(0, len(sampler), max(1, len(sampler) // 32)))
    obs = {"keypoint": batch["keypoint"], "state": batch["state"]}
    noise = torch.randn(len(batch["action"]), 16, 2, generator=torch.Generator().manual_seed(0))
    rk45 = policy.predict_action(obs, solver="rk45", noise=noise)
    euler = policy.predict_action(obs, solver="euler", steps=100, noise=noise)
    assert rk45.action.shape == (len(noise), 8, 2) and rk45.action_pred.shape == (len(noise), 16, 2)
    assert euler.nfe == 100 and rk45.nfe > 6
    # Push-T actions span about 500 px: Euler-100 must land within 0.5 % of that on average
    # (max 2 %), and far closer to the RK45 solution than a single Euler step does
    gap = (rk45.action_pred - euler.action_pred).abs()
    assert float(gap.mean()) < 2.5 and float(gap.max()) < 10.0, (float(gap.mean()), float(gap.max()))
    euler1 = policy.predict_action(obs, solver="euler", steps=1, noise=noise)
    assert float((rk45.action_pred - euler1.action_pred).abs().mean()) > 5 * float(gap.mean())
    one = policy.predict_action({"keypoint": batch["keypoint"][0], "state": batch["state"][0]},
                                solver="euler", steps=4)
    assert one.action.shape == (1, 8, 2) and one.nfe == 4
    np.testing.assert_array_equal(rk45.action.numpy(), rk45.action_pred[:, 1:9].numpy())


def test_resume_after_interruption_gives_identical_weights(pusht_store, tmp_path):
    overrides = PUSHT_LOWDIM + ["training.max_steps=30", "training.checkpoint_every=10",
                                "training.val_every=15", "training.batch_size=64"]
    whole = tmp_path / "whole"
    train(load_train_config(None, overrides), whole, pusht_store)

    class Interrupt(Exception):
        pass

    def stop_at_23(step, total, loss):
        if step == 23:
            raise Interrupt  # after the checkpoint at step 20, before the one at 30
    cut = tmp_path / "cut"
    with pytest.raises(Interrupt):
        train(load_train_config(None, overrides), cut, pusht_store,
              callbacks=Callbacks(on_step=stop_at_23))
    state = json.loads((cut / "checkpoints/latest/training_state/state.json").read_text())
    assert '"step"' in json.dumps(state)
    train(load_train_config(None, []), cut, pusht_store, resume=True)
    for name in ("model.safetensors", "ema.safetensors", "training_state/state.safetensors"):
        a = load_file(str(whole / "checkpoints/latest" / name))
        b = load_file(str(cut / "checkpoints/latest" / name))
        assert a.keys() == b.keys()
        for k in a:
            assert torch.equal(a[k], b[k]), (name, k)
    assert [r.get("train_loss") for r in records(whole)] == [r.get("train_loss") for r in records(cut)]


def test_corrupt_and_mismatched_checkpoints_are_clear_errors(trained, tmp_path):
    # a checkpoint without checksums.json (as written before issue 23; with it, every edit
    # below is a checksum mismatch first: tests/sefa_model_tests/test_finite.py) still gets these checks
    ckpt = tmp_path / "ckpt"
    shutil.copytree(trained / "checkpoints" / "latest", ckpt)
    (ckpt / "ema.safetensors").write_bytes(b"\x00" * 64)
    with pytest.raises(SefaInputError, match=r"ema.safetensors: checksum mismatch"):
        Policy.load(ckpt)
    (ckpt / "checksums.json").unlink()
    with pytest.raises(SefaInputError, match=r"ema.safetensors: corrupt safetensors file"):
        Policy.load(ckpt)
    shutil.rmtree(ckpt)
    shutil.copytree(trained / "checkpoints" / "latest", ckpt)
    (ckpt / "checksums.json").unlink()
    cfg = json.loads((ckpt / "config.json").read_text())
    cfg["train_config"]["policy"]["mlp_hidden_dims"] = [128, 128, 128]
    (ckpt / "config.json").write_text(json.dumps(cfg))
    with pytest.raises(SefaInputError, match=r"weights do not match the model in config.json"):
        Policy.load(ckpt)
    (ckpt / "config.json").write_text("{not json")
    with pytest.raises(SefaInputError, match=r"config.json: corrupt JSON"):
        Policy.load(ckpt)
    with pytest.raises(SefaInputError, match=r"no such checkpoint"):
        Policy.load(tmp_path / "nothing")


def test_unknown_config_key_suggests_the_nearest(tmp_path):
    with pytest.raises(SefaInputError, match=r"training: unknown key 'bach_size'; did you mean 'batch_size'\?"):
        load_train_config(None, ["training.bach_size=3"])
    r = subprocess.run([sys.executable, "-m", "sefa_cli.main", "train", "policy.horizn=8", "-w", str(tmp_path)],
                       capture_output=True, text=True, cwd=REPO)
    assert r.returncode == 1 and "did you mean 'horizon'?" in r.stderr


def test_ddp_two_processes_match_single_process(pusht_store, tmp_path):
    """torchrun, gloo backend, 2 CPU processes, global batch 64 (32 each) against one process
    with batch 64: the logged losses agree to 1e-4 relative and the weights to 1e-4 absolute
    (only the order of float reductions differs)."""
    overrides = PUSHT_LOWDIM + ["training.max_steps=12", "training.batch_size=64",
                                "training.log_every=4", "training.val_every=12",
                                "training.checkpoint_every=12", f"dataset={pusht_store}"]
    single = tmp_path / "single"
    r = subprocess.run([sys.executable, "-m", "sefa_cli.main", "train", *overrides, "--out", str(single)],
                       capture_output=True, text=True, cwd=REPO)
    assert r.returncode == 0, r.stderr
    ddp = tmp_path / "ddp"
    r = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", "2",
                        "--master_port", "29517", "-m", "sefa_cli.main", "train", *overrides,
                        "--out", str(ddp)], capture_output=True, text=True, cwd=REPO)
    assert r.returncode == 0, r.stderr
    assert "global batch 64 (32 per process x 2)" in r.stderr
    a, b = records(single), records(ddp)
    assert [x["step"] for x in a] == [x["step"] for x in b] == [4, 8, 12]
    np.testing.assert_allclose([x["train_loss"] for x in b], [x["train_loss"] for x in a], rtol=1e-4)
    wa = load_file(str(single / "checkpoints/latest/model.safetensors"))
    wb = load_file(str(ddp / "checkpoints/latest/model.safetensors"))
    for k in wa:
        torch.testing.assert_close(wb[k], wa[k], rtol=0, atol=1e-4)


@pytest.mark.parametrize("encoder", ["small", "resnet18"])
def test_image_policy_trains_and_predicts_from_uint8_frames(shared_data, tmp_path, monkeypatch,
                                                            encoder):
    """The image path end to end on real Push-T frames, for each image encoder: a few steps
    (random crop), a checkpoint, then `predict_action` from raw uint8 HWC images, which must give
    exactly what the trained weights gave in memory before they were written."""
    import copy

    import zarr

    import sefa_model.train.loop as training
    from conftest import pusht_image_store

    in_memory, write_checkpoint = {}, training.write_checkpoint

    def keep_and_write(directory, **parts):
        in_memory[directory.name] = copy.deepcopy(parts["ema"])  # the weights Policy.load reads
        write_checkpoint(directory, **parts)

    monkeypatch.setattr(training, "write_checkpoint", keep_and_write)
    src = zarr.open_group(str(shared_data / "pusht_cchi_v7_replay.zarr"), mode="r")
    store = pusht_image_store(shared_data, tmp_path)  # the first three real episodes
    cfg = load_train_config(None, [
        "shape_meta.obs.img.type=rgb", "shape_meta.obs.state.dims=[0,2]", "policy.head=mlp",
        "policy.crop_shape=[84,84]", "policy.mlp_hidden_dims=[64,64]", "training.batch_size=8",
        "training.max_steps=3", "training.val_every=3", "training.val_sample_windows=4",
        "training.val_batches=1", "flow.solver=euler", "flow.steps=2",
        f"policy.image_encoder={encoder}"])
    run = tmp_path / "run"
    train(cfg, run, store)
    saved = json.loads((run / "checkpoints/latest/config.json").read_text())["train_config"]
    assert saved["shape_meta"]["obs"]["img"]["shape"] == [3, 96, 96]
    assert saved["policy"]["image_encoder"] == encoder
    policy = Policy.load(run)
    assert type(policy.model.obs_encoder.image_encoders["rgb_img"]).__name__ == {
        "small": "ImageEncoder", "resnet18": "ResNet18Encoder"}[encoder]
    frames = src["data/img"][:2].astype(np.uint8)
    obs = {"img": frames, "state": src["data/state"][:2]}
    noise = torch.randn(1, 16, 2, generator=torch.Generator().manual_seed(0))
    out = policy.predict_action(obs, noise=noise)
    assert out.action.shape == (1, 8, 2) and out.nfe == 2
    assert torch.isfinite(out.action).all()
    before = Policy(policy.cfg, in_memory["latest"], policy.normalizer).predict_action(obs, noise=noise)
    assert torch.equal(out.action_pred, before.action_pred)


def test_pusht_rollout_eval_is_valid_and_reproducible(trained, tmp_path):
    pytest.importorskip("gym_pusht", reason="gym-pusht (the sim extra) is not installed")
    from sefa_sim.rollouts import evaluate_pusht

    a = evaluate_pusht(trained, n_test=3, max_steps=40, solver="euler", steps=2, out=tmp_path)
    b = evaluate_pusht(trained, n_test=3, max_steps=40, solver="euler", steps=2)
    assert [r["seed"] for r in a["per_seed"]] == [100000, 100001, 100002]
    assert all(0.0 <= r["score"] <= 1.0 and r["steps"] == 40 for r in a["per_seed"])
    assert a["per_seed"] == b["per_seed"]  # same seeds, same policy noise: same episodes
    saved = json.loads((tmp_path / "eval_log.json").read_text())
    assert saved["test/mean_score"] == pytest.approx(np.mean([r["score"] for r in a["per_seed"]]))
