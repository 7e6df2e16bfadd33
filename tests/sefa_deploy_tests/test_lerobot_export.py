"""`sefa export --format lerobot`: the LeRobot policy folder as sefa writes and reads it, without
LeRobot (sefa runs on Python 3.10+, LeRobot 0.5+ on 3.12+). Whether LeRobot's own loaders and
tools take it is integrations/lerobot/tests' job (scripts/lerobot_plugin_check.sh)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

from deploy_helpers import sefa, validation_windows
from sefa_data.errors import SefaInputError
from sefa_deploy.lerobot_export import export_lerobot
from sefa_deploy.lerobot_format import FILES, ChunkModel, check_files, input_map
from sefa_model.policy.artifact import Policy
from sefa_pipelines.lerobot_names import export_for_lerobot
from sefa_sim.pusht import GYM_PUSHT_CORNERS, LOCAL_KEYPOINTS, keypoints_from_pose

TOLERANCE = 1e-5  # normalized action units: the same float32 ops as predict_action


@pytest.fixture(scope="module")
def ws(deploy_workspace):
    return deploy_workspace


@pytest.fixture(scope="module")
def pusht(ws, tmp_path_factory):
    out = tmp_path_factory.mktemp("lerobot") / "pusht"
    export_for_lerobot(ws / "distill", out, key_map=None)
    return out


def load(folder) -> ChunkModel:
    config = json.loads((folder / "config.json").read_text())
    return ChunkModel(config["sefa"], config["solver"], config["steps"]).load(folder / "model.safetensors")


def normalized(policy: Policy, chunk) -> np.ndarray:
    p = policy.normalizer.params["action"]
    return np.asarray(chunk) * p.scale + p.offset


def test_the_folder_is_lerobots_layout_in_lerobots_names(pusht):
    assert sorted(p.name for p in pusht.iterdir()) == sorted(FILES)
    config = json.loads((pusht / "config.json").read_text())
    assert config["type"] == "sefa" and config["n_obs_steps"] == 2
    assert config["input_features"] == {
        "observation.environment_state": {"type": "ENV", "shape": [16]},  # gym-pusht's 8 corners
        "observation.state": {"type": "STATE", "shape": [2]}}  # the agent: state's dims [0, 2]
    assert config["output_features"] == {"action": {"type": "ACTION", "shape": [2]}}
    assert config["execution"] == {"mode": "receding", "replan_every": None, "samples": None,
                                   "decay": 0.9, "ensemble_k": 0.01, "weak": None}
    assert (config["solver"], config["steps"], config["sefa"]["kind"]) == ("euler", 1, "sefa_one_step")
    pre = json.loads((pusht / "policy_preprocessor.json").read_text())
    assert [s["registry_name"] for s in pre["steps"]] == [
        "rename_observations_processor", "to_batch_processor", "device_processor"]
    tensors = load_file(str(pusht / "model.safetensors"))
    assert {k for k in tensors if k.startswith("normalizer.")} == {
        f"normalizer.{k}.{p}" for k in ("action", "keypoint", "state") for p in ("scale", "offset")}


def test_gym_pushts_corners_give_the_actions_of_the_store_keypoints(ws, pusht):
    """On 100 validation windows: the corners placed by each frame's block pose, through the
    folder, against predict_action on the store's 9 keypoints placed by the same pose (what
    `sefa eval --env pusht` feeds), same noise."""
    policy = Policy.load(ws / "distill", device="cpu")
    obs = validation_windows(policy, ws / "dataset.zarr")
    pose = obs["state"][..., 2:5].astype(np.float64)  # (B, To, 3)
    keypoints = keypoints_from_pose(pose, LOCAL_KEYPOINTS).astype(np.float32)
    corners = keypoints_from_pose(pose, GYM_PUSHT_CORNERS).reshape(*pose.shape[:2], 16)
    noise = torch.randn(len(pose), 16, 2, generator=torch.Generator().manual_seed(0))
    with torch.inference_mode():
        got = load(pusht)({"observation.environment_state": torch.tensor(corners, dtype=torch.float32),
                           "observation.state": torch.tensor(obs["state"][..., :2])}, noise)
    want = policy.predict_action({"keypoint": keypoints, "state": obs["state"]}, noise=noise)
    assert len(pose) == 100
    assert np.abs(normalized(policy, got) - normalized(policy, want.action_pred)).max() < 1e-4


def test_a_plain_key_map_is_predict_action_exactly(ws, tmp_path):
    """The keypoints passed as they are (--key-map observation.keypoint=keypoint) and the whole
    5-value state: the folder's chunk is predict_action's on 100 validation windows."""
    out = tmp_path / "plain"
    export_for_lerobot(ws / "distill", out, key_map={"observation.keypoint": "keypoint"})
    config = json.loads((out / "config.json").read_text())
    assert config["input_features"]["observation.keypoint"] == {"type": "STATE", "shape": [18]}
    policy = Policy.load(ws / "distill", device="cpu")
    obs = validation_windows(policy, ws / "dataset.zarr")
    noise = torch.randn(len(obs["state"]), 16, 2, generator=torch.Generator().manual_seed(1))
    with torch.inference_mode():
        got = load(out)({"observation.keypoint": torch.tensor(obs["keypoint"]).flatten(2),
                         "observation.state": torch.tensor(obs["state"])}, noise)
    want = policy.predict_action(obs, noise=noise).action_pred
    assert np.abs(normalized(policy, got) - normalized(policy, want)).max() <= TOLERANCE


def test_a_state_of_another_width_is_one_line(pusht):
    with pytest.raises(SefaInputError, match=r"'observation.state' has 3 values a frame; the policy "
                                             r"reads 2 or 5 \(store key 'state'\)"):
        load(pusht)({"observation.environment_state": torch.zeros(1, 2, 16),
                     "observation.state": torch.zeros(1, 2, 3)}, torch.zeros(1, 16, 2))


def test_an_observation_lerobot_cannot_name_is_one_line(ws):
    """A policy reading a key with no LeRobot name (Push-T's n_contacts, say) is refused at
    export with the --key-map that names it."""
    policy = Policy.load(ws / "distill", device="cpu")
    cfg = policy.cfg
    cfg.shape_meta.obs = {"n_contacts": cfg.shape_meta.obs["state"], **cfg.shape_meta.obs}
    with pytest.raises(SefaInputError, match=r"LeRobot has no name for the policy's observation "
                                             r"'n_contacts'.*--key-map observation.NAME=n_contacts"):
        input_map(cfg)


@pytest.mark.parametrize("key_map, line", [
    (["observation.state=keypoint"], "'keypoint' and 'state' would both be LeRobot's 'observation.state'"),
    (["state_vec=state"], "'state_vec' for 'state': LeRobot's observation names start with 'observation.'"),
    (["observation.image=state"], "'state' is low-dim: LeRobot needs a name that is not an image's"),
    (["observation.x=nothing"], "the policy reads no observation 'nothing'"),
])
def test_bad_key_maps_are_one_line_and_write_nothing(ws, tmp_path, key_map, line):
    args = [a for item in key_map for a in ("--key-map", item)]
    r = sefa("export", ws / "distill", "--format", "lerobot", "--out", tmp_path / "x", *args,
             "--json", check=False)
    assert r.returncode == 1 and r.stderr.count("\n") == 1 and line in r.stderr, r.stderr
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("args, line", [
    (["--execution", "ensemble", "--replan-every", "9"], "--replan-every: 9 is outside 1..8"),
    (["--execution", "bid"], "--execution: bid contrasts the policy with a weaker one"),
    (["--execution", "receding", "--samples", "4"], "--samples: 4 samples need the coherent or bid mode"),
])
def test_execution_settings_are_checked_at_export(ws, tmp_path, args, line):
    r = sefa("export", ws / "distill", "--format", "lerobot", "--out", tmp_path / "x", *args,
             "--json", check=False)
    assert r.returncode == 1 and r.stderr.count("\n") == 1 and line in r.stderr, r.stderr
    assert list(tmp_path.iterdir()) == []


def test_the_execution_asked_or_chosen_is_the_folders(ws, tmp_path):
    """--execution options go into config.json as given; without them, the execution chosen
    for the policy (sefa choose-execution's record) when there is one."""
    from sefa_model.policy.execution import ExecutionSettings, save_choice

    r = sefa("export", ws / "distill", "--format", "lerobot", "--out", tmp_path / "y",
             "--execution", "ensemble", "--ensemble-k", "0.1", "--json")
    assert json.loads(r.stdout)["execution"]["mode"] == "ensemble"
    config = json.loads((tmp_path / "y" / "config.json").read_text())
    assert (config["execution"]["mode"], config["execution"]["ensemble_k"]) == ("ensemble", 0.1)
    chosen = ExecutionSettings("coherent", replan_every=2, samples=8).resolved(8)
    save_choice(ws / "distill", chosen, "euler-1", {})
    try:
        export_for_lerobot(ws / "distill", tmp_path / "z", key_map=None)
    finally:
        (ws / "distill" / "checkpoints" / "latest" / "execution.json").unlink()
    config = json.loads((tmp_path / "z" / "config.json").read_text())
    assert ExecutionSettings.from_json(config["execution"]) == chosen


def test_a_folder_missing_a_file_or_holding_odd_weights_is_one_line(pusht, tmp_path):
    import shutil

    from safetensors.torch import save_file

    folder = tmp_path / "f"
    shutil.copytree(pusht, folder)
    (folder / "model.safetensors").unlink()
    with pytest.raises(SefaInputError, match=r"model.safetensors: missing: a sefa policy folder"):
        check_files(folder)
    tensors = load_file(str(pusht / "model.safetensors"))
    tensors["normalizer.state.scale"] = tensors["normalizer.state.scale"] * float("nan")
    save_file(tensors, str(folder / "model.safetensors"))
    with pytest.raises(SefaInputError, match="non-finite weights: normalizer.state.scale"):
        load(folder)
    del tensors["normalizer.state.scale"], tensors["normalizer.state.offset"]
    save_file(tensors, str(folder / "model.safetensors"))
    with pytest.raises(SefaInputError, match="arrays do not match the keys"):
        load(folder)


def test_an_existing_folder_that_is_no_policy_folder_is_kept(ws, tmp_path):
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep")
    with pytest.raises(SefaInputError, match="exists and is not a policy folder"):
        export_lerobot(ws / "distill", tmp_path / "mine")
    assert (tmp_path / "mine" / "notes.txt").read_text() == "keep"


def test_a_camera_policy_reads_lerobots_float_chw_frames(shared_data, tmp_path):
    """Push-T's camera (the store's uint8 HWC `img`) becomes LeRobot's `observation.image`
    (float CHW in [0, 1], as LeRobot's env and robot processors hand it over); the folder's
    chunk on those frames is predict_action's on the store's."""
    from conftest import TINY_IMAGE_TRAIN, pusht_image_store

    from sefa_model.config import load_train_config
    from sefa_model.train.loop import train

    store = pusht_image_store(shared_data, tmp_path)
    train(load_train_config(None, TINY_IMAGE_TRAIN), tmp_path / "run", store)
    config = export_for_lerobot(tmp_path / "run", tmp_path / "lerobot", key_map=None)
    assert config["input_features"] == {"observation.image": {"type": "VISUAL", "shape": [3, 96, 96]},
                                        "observation.state": {"type": "STATE", "shape": [2]}}
    policy = Policy.load(tmp_path / "run", device="cpu")
    obs = validation_windows(policy, store, 6)
    noise = torch.randn(len(obs["img"]), 16, 2, generator=torch.Generator().manual_seed(4))
    frames = torch.from_numpy(obs["img"]).permute(0, 1, 4, 2, 3).float() / 255
    with torch.inference_mode():
        got = load(tmp_path / "lerobot")({"observation.image": frames,
                                          "observation.state": torch.tensor(obs["state"][..., :2])},
                                         noise)
    want = policy.predict_action(obs, noise=noise).action_pred
    assert np.abs(normalized(policy, got) - normalized(policy, want)).max() < 1e-4
