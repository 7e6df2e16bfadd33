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
from sefa_model.checkpoint import write_checksums
from sefa_model.policy import Policy
from sefa_model.policy_data import PolicyData


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
    from sefa_data.zarr_store import EpisodeStore

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
