"""The processor: one transform between a robot's (or the store's) arrays and the network's
inputs, shared by training, predict_action, the export and the server's request checks."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch

from deploy_helpers import validation_windows
from sefa_data.errors import SefaInputError
from sefa_model.policy.checkpoint import write_checksums
from sefa_model.policy.artifact import Policy
from sefa_model.data.windows import PolicyData


@pytest.fixture(scope="module")
def one_step(deploy_workspace):
    return deploy_workspace / "distill" / "checkpoints" / "latest"


def test_numpy_and_tensor_observations_give_the_same_model_inputs(deploy_workspace, one_step):
    policy = Policy.load(one_step, device="cpu")
    obs = validation_windows(policy, deploy_workspace / "dataset.zarr", n=8)
    from_numpy = policy.processor.obs(obs)
    from_tensors = policy.processor.obs({k: torch.from_numpy(v) for k, v in obs.items()})
    for key in obs:
        assert torch.equal(from_numpy[key], from_tensors[key]), key


def test_training_and_inference_see_the_same_inputs(deploy_workspace, one_step):
    """What training feeds the network for a window is what predict_action feeds it for the
    same window's raw arrays (state is the `dims`-sliced, normalized agent position)."""
    from sefa_data.store.zarr_store import EpisodeStore

    policy = Policy.load(one_step, device="cpu")
    data = PolicyData(policy.cfg, EpisodeStore.open(deploy_workspace / "dataset.zarr"),
                      policy.normalizer)
    idx = np.arange(0, 40, 5)
    train_inputs, _ = data.tensors(data.train, idx, torch.device("cpu"))
    raw = data.train.batch(idx)
    served = policy.prepare_obs({k: raw[k] for k in policy.cfg.shape_meta.obs})
    for key in train_inputs:
        assert torch.equal(train_inputs[key], served[key]), key
    assert served["state"].shape[-1] == 2  # the dims slice [0, 2]


def test_a_checkpoint_without_processor_json_still_loads_and_predicts_the_same(
        deploy_workspace, one_step, tmp_path):
    old = tmp_path / "old"
    shutil.copytree(one_step, old)
    (old / "processor.json").unlink()  # as written before issue 22 (and before checksums)
    (old / "checksums.json").unlink()
    obs = validation_windows(Policy.load(one_step, device="cpu"), deploy_workspace / "dataset.zarr", n=4)
    noise = torch.randn(4, 16, 2, generator=torch.Generator().manual_seed(0))
    want = Policy.load(one_step, device="cpu").predict_action(obs, noise=noise).action_pred
    got = Policy.load(old, device="cpu").predict_action(obs, noise=noise).action_pred
    assert torch.equal(want, got)


def test_a_processor_json_that_disagrees_with_the_config_is_refused(one_step, tmp_path):
    edited = tmp_path / "edited"
    shutil.copytree(one_step, edited)
    config = json.loads((edited / "config.json").read_text())
    config["train_config"]["shape_meta"]["obs"]["state"]["dims"] = [0, 1]  # edited by hand
    (edited / "config.json").write_text(json.dumps(config))
    write_checksums(edited)  # consistent checksums: processor.json's own check must catch it
    with pytest.raises(SefaInputError, match="processor.json does not match"):
        Policy.load(edited, device="cpu")


def test_the_export_wraps_the_policys_own_processor(one_step):
    from sefa_deploy.export import ExportedPolicy

    policy = Policy.load(one_step, device="cpu")
    assert ExportedPolicy(policy, "euler", 1).processor is policy.processor


def test_a_large_camera_is_resized_to_a_model_size_everywhere(shared_data, tmp_path):
    """Two real Push-T episodes whose 96x96 frames are enlarged to 192x256 (pixel repeats,
    written with zarr): training resizes them to 96x128 by default (the short side to 96), the
    checkpoint says so (config.json and processor.json), predict_action and the exported ONNX
    take the recorded 192x256 frames and resize them the same way; policy.resize_shape and a
    key's own resize choose another size."""
    import zarr

    from conftest import TINY_IMAGE_TRAIN
    from sefa_data.ingest import IngestOptions, ingest
    from sefa_deploy.export import export_policy
    from sefa_model.config import load_train_config
    from sefa_model.policy.model import describe_observation, observation_record, resolve_shapes
    from sefa_model.policy.processor import resize_images
    from sefa_model.train.loop import train
    from sefa_data.store.zarr_store import EpisodeStore

    src = zarr.open_group(str(shared_data / "pusht_cchi_v7_replay.zarr"), mode="r")
    ends = src["meta/episode_ends"][:2]
    big = np.repeat(np.repeat(src["data"]["img"][: ends[-1]], 2, axis=1), [2, 3] * 48, axis=2)
    assert big.shape[1:] == (192, 240, 3)
    root = zarr.open_group(str(tmp_path / "small.zarr"), mode="w", zarr_format=2)
    root.create_array("data/img", data=big)
    for key in ("state", "action"):
        root.create_array(f"data/{key}", data=src["data"][key][: ends[-1]])
    root.create_array("meta/episode_ends", data=ends)
    ingest([tmp_path / "small.zarr"], tmp_path / "s.zarr", IngestOptions(fps=10))
    store = EpisodeStore.open(tmp_path / "s.zarr")

    cfg = load_train_config(None, TINY_IMAGE_TRAIN + ["training.max_steps=2"])
    record = observation_record(resolve_shapes(load_train_config(None, TINY_IMAGE_TRAIN), store))
    assert record["img"]["resize"] == [96, 120] and record["img"]["shape"] == [3, 96, 120]
    assert "img (192, 240, 3) rgb resized to 96x120" in describe_observation("img", record["img"])
    # (a crop fits within the model size: TINY_IMAGE_TRAIN's 84x84 does not fit 64x80)
    for extra, want in ((["policy.resize_shape=[64,80]", "policy.crop_shape=[56,72]"], [64, 80]),
                        (["shape_meta.obs.img.resize=[192,240]"], None)):  # the recorded size
        r = observation_record(resolve_shapes(load_train_config(None, TINY_IMAGE_TRAIN + extra), store))
        assert r["img"].get("resize") == want

    train(cfg, tmp_path / "run", tmp_path / "s.zarr")
    saved = json.loads((tmp_path / "run/checkpoints/latest/config.json").read_text())
    assert saved["train_config"]["shape_meta"]["obs"]["img"]["resize"] == [96, 120]
    steps = json.loads((tmp_path / "run/checkpoints/latest/processor.json").read_text())
    assert {"resize": [96, 120], "interpolation": "bilinear, antialiased"} in steps["obs"]["img"]["steps"]

    policy = Policy.load(tmp_path / "run", device="cpu")
    obs = validation_windows(policy, tmp_path / "s.zarr", 4)
    assert obs["img"].shape[2:] == (192, 240, 3)
    seen = policy.processor.obs.one("img", torch.from_numpy(obs["img"]))
    frames = torch.from_numpy(obs["img"]).movedim(-1, -3).float() / 255
    torch.testing.assert_close(seen, resize_images(frames, [96, 120]), rtol=0, atol=0)
    assert seen.shape[2:] == (3, 96, 120)
    meta = export_policy(tmp_path / "run", tmp_path / "onnx", fmt="onnx")  # parity-checked
    assert meta["obs"]["img"]["shape"] == [2, 192, 240, 3]
