"""The SeFA stages as the reference runs them (issue 11): reflow and distillation keep the base
policy's observation encoder frozen and train on its features, computed once per window; the
student records the time it was trained at and sampling reads it from the checkpoint.

The image store is the first three real Push-T episodes (../shared/data), copied with zarr's
own writer; the networks are tiny so that each training takes seconds.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

from conftest import TINY_IMAGE_TRAIN
from sefa_pipelines.stages import student_config
from sefa_data.errors import SefaInputError
from sefa_model.train import loop as training
from sefa_model.policy.checkpoint import write_checksums
from sefa_model.config import load_train_config
from sefa_model.policy.artifact import Policy
from sefa_model.sefa.reflow import CouplingConfig, generate_couplings
from sefa_model.data.couplings import PairSource
from sefa_model.data.windows import PolicyData
from sefa_model.train.batches import batch_indices
from sefa_model.train.loop import train

IMAGE_BASE = TINY_IMAGE_TRAIN
STUDENT = ["training.max_steps=3", "training.checkpoint_every=3", "training.val_every=3"]


@pytest.fixture(scope="module")
def image_ws(shared_data, tmp_path_factory) -> dict:
    from conftest import pusht_image_store

    tmp = tmp_path_factory.mktemp("frozen")
    store = pusht_image_store(shared_data, tmp)
    base = load_train_config(None, IMAGE_BASE + ["training.keep_every=2"])
    train(base, tmp / "base", store)
    policy = Policy.load(tmp / "base", device="cpu")
    generate_couplings(policy, store, tmp / "couplings.zarr",
                       CouplingConfig(samples_per_window=2, solver="euler", steps=2, max_windows=6))
    return {"dir": tmp, "store": store, "base": tmp / "base" / "checkpoints" / "latest",
            "couplings": tmp / "couplings.zarr", "base_cfg": base}


def distill(ws: dict, out: Path, overrides: list[str], steps: int = 1) -> Path:
    cfg = student_config(load_train_config(None, IMAGE_BASE), STUDENT + overrides, steps=steps)
    train(cfg, out, ws["store"], init_from=ws["base"],
          couplings=PairSource.couplings(ws["couplings"], "sefa_one_step"))
    return out / "checkpoints" / "latest"


def encoder_weights(path: Path, file: str) -> dict[str, torch.Tensor]:
    return {k: v for k, v in load_file(str(path / file)).items() if k.startswith("obs_encoder.")}


def test_student_keeps_the_base_encoder_by_default_and_fine_tunes_on_request(image_ws, tmp_path):
    base = encoder_weights(image_ws["base"], "ema.safetensors")  # what the couplings were made with
    assert base  # the image encoder has weights to keep
    frozen = distill(image_ws, tmp_path / "frozen", [])
    for file in ("model.safetensors", "ema.safetensors"):
        got = encoder_weights(frozen, file)
        assert got.keys() == base.keys()
        assert all(torch.equal(got[k], base[k]) for k in base), file
    meta = json.loads((frozen / "config.json").read_text())
    assert meta["train_config"]["training"]["freeze_encoder"] is True
    assert meta["encoder"].startswith("frozen")
    # the head did train
    head_before = load_file(str(image_ws["base"] / "ema.safetensors"))
    head_after = load_file(str(frozen / "model.safetensors"))
    assert any(not torch.equal(head_before[k], head_after[k]) for k in head_after if k.startswith("head."))

    tuned = distill(image_ws, tmp_path / "tuned", ["training.freeze_encoder=false"])
    got = encoder_weights(tuned, "model.safetensors")
    assert any(not torch.equal(got[k], base[k]) for k in base)
    meta = json.loads((tuned / "config.json").read_text())
    assert meta["encoder"].startswith("fine-tuned") and not meta["train_config"]["training"]["freeze_encoder"]


def test_student_conditions_on_the_base_encoders_features(image_ws, tmp_path, monkeypatch):
    """The condition the student's first step trains on equals the base policy's encoding of
    those windows (eval mode, center crop), row for row."""
    seen = []
    original = training.FlowPolicyModel.forward

    def spy(self, obs, x, t):
        seen.append(obs.detach().clone() if torch.is_tensor(obs) else None)
        return original(self, obs, x, t)

    monkeypatch.setattr(training.FlowPolicyModel, "forward", spy)
    distill(image_ws, tmp_path / "s", [])
    monkeypatch.undo()
    # the 3 training steps get features, never observations (validation, after them, encodes)
    assert len(seen) >= 3 and all(c is not None for c in seen[:3])

    import zarr

    window = zarr.open_group(str(image_ws["couplings"]), mode="r")["window"][:]
    idx = batch_indices(42, 0, len(window), 8)
    base = Policy.load(image_ws["base"], device="cpu")
    data = PolicyData(base.cfg, base_store(image_ws), base.normalizer)
    obs, _ = data.tensors(data.train, window[idx], torch.device("cpu"))
    with torch.no_grad():
        expected = base.model.encode(obs)
    torch.testing.assert_close(seen[0], expected, rtol=0, atol=1e-6)


def base_store(ws):
    from sefa_data.store.zarr_store import EpisodeStore

    return EpisodeStore.open(ws["store"])


def test_freezing_the_encoder_of_the_base_flow_is_refused(image_ws, tmp_path):
    cfg = load_train_config(None, IMAGE_BASE + ["training.freeze_encoder=true"])
    with pytest.raises(SefaInputError, match="freeze_encoder"):
        train(cfg, tmp_path / "x", image_ws["store"])


def test_student_records_its_training_time_and_sampling_reads_it(image_ws, tmp_path):
    student = distill(image_ws, tmp_path / "s", [])
    meta = json.loads((student / "config.json").read_text())
    assert meta["flow_convention"]["t_train"] == "0 (one step)"
    assert meta["train_config"]["flow"]["t_train"] == "start"
    policy = Policy.load(student, device="cpu")
    obs = {"img": np.zeros((2, 96, 96, 3), np.uint8), "state": np.zeros((2, 5), np.float32)}
    with pytest.raises(SefaInputError, match="one Euler step"):
        policy.predict_action(obs, solver="rk45")

    # a student trained at t = 0.3 (say) samples from 0.3: x0 + (1 - 0.3) v(x0, 0.3)
    moved = tmp_path / "moved"
    shutil.copytree(student, moved)
    meta["train_config"]["flow"]["t_eps"] = 0.3
    (moved / "config.json").write_text(json.dumps(meta))
    write_checksums(moved)  # edited on purpose
    policy = Policy.load(moved, device="cpu")
    noise = torch.randn(1, 16, 2, generator=torch.Generator().manual_seed(0))
    out = policy.predict_action(obs, noise=noise)
    with torch.no_grad():
        cond = policy.model.encode(policy.prepare_obs(obs))
        x = noise + 0.7 * policy.model.velocity(noise, torch.full((1,), 0.3), cond)
    expected = policy.normalizer.unnormalize("action", x)
    torch.testing.assert_close(out.action_pred, expected, rtol=0, atol=1e-5)
    assert out.nfe == 1


def test_a_k_step_student_trains_at_its_euler_times_and_samples_with_them(image_ws, tmp_path,
                                                                          monkeypatch):
    """`sefa distill --steps 2`: the velocity is trained at t = 0 and 0.5 only (the times two
    Euler steps visit), the checkpoint says so, and sampling takes exactly those two steps."""
    from sefa_model.train import batches as train_batches

    seen = []
    fetch = train_batches.CouplingPairs.fetch
    monkeypatch.setattr(train_batches.CouplingPairs, "fetch",
                        lambda self, *a: seen.append((b := fetch(self, *a))["t"]) or b)
    student = distill(image_ws, tmp_path / "s2", [], steps=2)
    times = torch.cat(seen)
    assert set(times.tolist()) == {0.0, 0.5} and len(times) >= 8
    meta = json.loads((student / "config.json").read_text())
    assert (meta["train_config"]["flow"]["t_train"], meta["train_config"]["flow"]["steps"]) == ("grid", 2)

    policy = Policy.load(student, device="cpu")
    obs = {"img": np.zeros((2, 96, 96, 3), np.uint8), "state": np.zeros((2, 5), np.float32)}
    with pytest.raises(SefaInputError, match="2 Euler steps"):
        policy.predict_action(obs, solver="euler", steps=1)
    noise = torch.randn(1, 16, 2, generator=torch.Generator().manual_seed(0))
    out = policy.predict_action(obs, noise=noise)
    with torch.no_grad():
        cond = policy.model.encode(policy.prepare_obs(obs))
        x = noise + 0.5 * policy.model.velocity(noise, torch.zeros(1), cond)
        x = x + 0.5 * policy.model.velocity(x, torch.full((1,), 0.5), cond)
    torch.testing.assert_close(out.action_pred, policy.normalizer.unnormalize("action", x),
                               rtol=0, atol=1e-5)
    assert out.nfe == 2


def test_a_base_copied_without_its_optimizer_state_is_distilled_alike(image_ws, tmp_path):
    """A base flow trained elsewhere often comes back as what a policy needs (config, EMA
    weights, normalizer, processor; the GPU study of issue 26 did): a distillation reads only
    those, so it starts from such a copy and trains the same student; what it reads is still
    checked (a flipped bit in the EMA weights is refused before any training)."""
    lean = tmp_path / "lean"
    shutil.copytree(image_ws["base"], lean)
    shutil.rmtree(lean / "training_state")
    (lean / "model.safetensors").unlink()
    full = distill(image_ws, tmp_path / "from_full", [])
    ws = {**image_ws, "base": lean}
    copy = distill(ws, tmp_path / "from_lean", [])
    a, b = load_file(str(full / "ema.safetensors")), load_file(str(copy / "ema.safetensors"))
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)

    ema = bytearray((lean / "ema.safetensors").read_bytes())
    ema[-5] ^= 0x01
    (lean / "ema.safetensors").write_bytes(bytes(ema))
    with pytest.raises(SefaInputError, match="checksum mismatch"):
        distill(ws, tmp_path / "from_damaged", [])
    assert not (tmp_path / "from_damaged" / "checkpoints").exists()


def test_keep_every_keeps_each_step_checkpoint(image_ws):
    """A budget curve evaluates checkpoints along one run: step_2 and step_4 are kept beside
    latest, loadable, and step_4 is latest."""
    ckpts = image_ws["base"].parent
    assert sorted(p.name for p in ckpts.iterdir()) == ["best", "latest", "step_2", "step_4"]
    two, four = (load_file(str(ckpts / f"step_{n}" / "model.safetensors")) for n in (2, 4))
    latest = load_file(str(ckpts / "latest" / "model.safetensors"))
    assert all(torch.equal(four[k], latest[k]) for k in latest)
    assert any(not torch.equal(two[k], four[k]) for k in two)
    assert Policy.load(ckpts / "step_2", device="cpu").cfg.training.keep_every == 2


def test_a_run_stopped_along_a_longer_schedule_is_that_schedules_checkpoint(image_ws, tmp_path):
    """training.lr_decay_steps: 3 steps of a 4-step cosine schedule give exactly the 4-step run's
    step_3 weights (the `cpu` profile's base is step 30,000 of a 50,000-step schedule); 3 steps of
    its own 3-step schedule do not. Derived stages set their own length and drop it."""
    every = ["training.checkpoint_every=1", "training.val_every=4"]
    train(load_train_config(None, IMAGE_BASE + every + ["training.keep_every=3"]), tmp_path / "ref",
          image_ws["store"])
    three = every + ["training.max_steps=3"]
    train(load_train_config(None, IMAGE_BASE + three + ["training.lr_decay_steps=4"]), tmp_path / "along",
          image_ws["store"])
    train(load_train_config(None, IMAGE_BASE + three), tmp_path / "own", image_ws["store"])
    step_3 = load_file(str(tmp_path / "ref" / "checkpoints" / "step_3" / "model.safetensors"))
    along, own = (load_file(str(tmp_path / run / "checkpoints" / "latest" / "model.safetensors"))
                  for run in ("along", "own"))
    assert all(torch.equal(along[k], step_3[k]) for k in step_3)
    assert any(not torch.equal(own[k], step_3[k]) for k in step_3)
    # continuing a run that had already finished trains nothing and reports no loss (not NaN,
    # which no JSON summary can hold)
    again = train(load_train_config(None, IMAGE_BASE + three), tmp_path / "own", image_ws["store"],
                  resume=True)
    assert (again.steps, again.train_loss) == (3, None)
    json.dumps(again.__dict__, allow_nan=False)
    cfg = load_train_config(None, IMAGE_BASE + ["training.lr_decay_steps=50"])
    assert student_config(cfg, STUDENT).training.lr_decay_steps is None
    with pytest.raises(Exception, match="lr_decay_steps"):
        load_train_config(None, IMAGE_BASE + ["training.lr_decay_steps=3"])


def test_training_writes_tensorboard_events_and_a_curve_plot(image_ws):
    """Every training leaves TensorBoard event files with its loss and validation series, read
    back with TensorBoard's own reader, and curves.png beside logs.jsonl."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    run = image_ws["base"].parent.parent
    events = EventAccumulator(str(run / "tensorboard"))
    events.Reload()
    tags = set(events.Tags()["scalars"])
    assert {"train/loss", "val/action_mse", "val/mean_action_mse", "lr"} <= tags
    logged = [json.loads(line) for line in (run / "logs.jsonl").read_text().splitlines()]
    val_steps = [r["step"] for r in logged if "val_action_mse" in r]
    assert [e.step for e in events.Scalars("val/action_mse")] == val_steps
    assert [e.value for e in events.Scalars("val/action_mse")] == pytest.approx(
        [r["val_action_mse"] for r in logged if "val_action_mse" in r], rel=1e-6)
    png = (run / "curves.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 5000


def test_frozen_features_are_computed_once_and_read_by_the_next_stage(image_ws, tmp_path, monkeypatch):
    """Issue 14: with a features cache, the first stage with the frozen encoder encodes the
    windows once; the next one (here a second student, then coupling generation) reads them,
    and they equal a fresh encoding. Another encoder (the step-2 checkpoint) misses the cache."""
    from sefa_model.data import features as features_mod

    cache = tmp_path / "features"
    calls = []
    real = features_mod.window_features
    monkeypatch.setattr(features_mod, "window_features",
                        lambda *a, **k: calls.append(len(a[2])) or real(*a, **k))

    def student(name: str, init: Path) -> None:
        cfg = student_config(load_train_config(None, IMAGE_BASE), STUDENT)
        train(cfg, tmp_path / name, image_ws["store"], init_from=init, features_cache=cache,
              couplings=PairSource.couplings(image_ws["couplings"], "sefa_one_step"))

    student("a", image_ws["base"])
    assert calls == [6]  # the 6 windows of the couplings, encoded once
    (entry,) = cache.iterdir()
    stored = load_file(str(entry / "features.safetensors"))
    assert stored["windows"].tolist() == sorted(set(stored["windows"].tolist()))
    base = Policy.load(image_ws["base"], device="cpu")
    data = PolicyData(base.cfg, base_store(image_ws), base.normalizer)
    fresh = real(base.model, data, stored["windows"].numpy(), torch.device("cpu"))
    torch.testing.assert_close(stored["features"], fresh, rtol=0, atol=0)

    student("b", image_ws["base"])
    assert calls == [6]  # read, not encoded again
    # coupling generation from the base policy, same windows: also a hit, and the same couplings
    subset = CouplingConfig(samples_per_window=2, solver="euler", steps=2, max_windows=6)
    generate_couplings(base, image_ws["store"], tmp_path / "c.zarr", subset, features_cache=cache)
    assert calls == [6]
    import zarr

    ours = zarr.open_group(str(tmp_path / "c.zarr"), mode="r")["action"][:]
    theirs = zarr.open_group(str(image_ws["couplings"]), mode="r")["action"][:]
    np.testing.assert_allclose(ours, theirs, rtol=0, atol=1e-5)

    student("c", image_ws["base"].parent / "step_2")  # another encoder: its own entry
    assert calls == [6, 6] and len(list(cache.iterdir())) == 2


def test_a_features_writer_killed_before_its_rename_leaves_no_entry(image_ws, tmp_path):
    """Fault injection (SEFA_FAULT=features.written: SIGKILL after the features are written to
    the temporary folder, before it is renamed): no entry is published, and the next call
    computes it and removes the killed writer's leftovers."""
    import os
    import subprocess
    import sys

    cache = tmp_path / "features"
    script = (
        "import sys, numpy as np, torch\n"
        "from sefa_data.store.zarr_store import EpisodeStore\n"
        "from sefa_model.data.features import cached_window_features\n"
        "from sefa_model.policy.artifact import Policy\n"
        "from sefa_model.data.windows import PolicyData\n"
        "p = Policy.load(sys.argv[1], device='cpu')\n"
        "d = PolicyData(p.cfg, EpisodeStore.open(sys.argv[2]), p.normalizer)\n"
        "cached_window_features(p.model, d, np.arange(4), torch.device('cpu'), sys.argv[3])\n")
    env = {**os.environ, "SEFA_FAULT": "features.written", "OMP_NUM_THREADS": "1"}
    r = subprocess.run([sys.executable, "-c", script, str(image_ws["base"]), str(image_ws["store"]),
                        str(cache)], env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == -9, r.stderr[-2000:]
    leftovers = [p.name for p in cache.iterdir()]
    assert len(leftovers) == 1 and ".tmp-" in leftovers[0]  # built, never published

    from sefa_model.data.features import cached_window_features

    base = Policy.load(image_ws["base"], device="cpu")
    data = PolicyData(base.cfg, base_store(image_ws), base.normalizer)
    got = cached_window_features(base.model, data, np.arange(4), torch.device("cpu"), cache)
    (entry,) = list(cache.iterdir())
    assert not entry.name.startswith(".")
    torch.testing.assert_close(load_file(str(entry / "features.safetensors"))["features"], got)
