"""The plugin inside LeRobot's own loaders: the export loads through LeRobot's config registry,
policy factory and processor pipelines, and its actions are sefa's `predict_action`'s."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys

import numpy as np
import pytest
import torch

from lerobot.configs.policies import PreTrainedConfig
from lerobot.policies.factory import get_policy_class, make_pre_post_processors

import lerobot_policy_sefa  # noqa: F401  (registers the type, as LeRobot's tools do)


def load(folder, overrides: dict | None = None):
    """As lerobot-eval loads a policy: config (with --policy.KEY=VALUE `overrides`), class by
    type, weights, processors with its overrides."""
    cfg = PreTrainedConfig.from_pretrained(folder, cli_overrides=[
        f"--{k}={v}" for k, v in (overrides or {}).items()])
    policy = get_policy_class(cfg.type).from_pretrained(folder, config=cfg)
    pre, post = make_pre_post_processors(cfg, pretrained_path=str(folder), preprocessor_overrides={
        "device_processor": {"device": "cpu"}, "rename_observations_processor": {"rename_map": {}}})
    return policy, pre, post


def store_frames(ws, n: int = 12) -> dict[str, np.ndarray]:
    import zarr

    data = zarr.open_group(str(ws / "dataset.zarr"), mode="r")["data"]
    return {k: np.asarray(data[k][:n], np.float32) for k in ("keypoint", "state")}


def test_lerobot_loads_the_export_with_its_registered_type(exports):
    policy, pre, post = load(exports["pusht"])
    assert type(policy).__name__ == "SefaPolicy" and policy.config.type == "sefa"
    assert [s.__class__.__name__ for s in pre.steps] == [
        "RenameObservationsProcessorStep", "AddBatchDimensionProcessorStep", "DeviceProcessorStep"]
    assert set(policy.config.input_features) == {"observation.environment_state", "observation.state"}
    assert policy.config.input_features["observation.environment_state"].shape == (16,)


def test_pusht_corners_give_the_actions_of_the_store_keypoints(exports):
    """gym-pusht's 8 corners (LeRobot's environment state), placed by the store's block poses,
    through LeRobot's processors and the plugin, against sefa's predict_action on the store's
    9 keypoints placed by the same poses, with the same noise."""
    from sefa_model.policy import Policy
    from sefa_sim.pusht import GYM_PUSHT_CORNERS, LOCAL_KEYPOINTS, keypoints_from_pose

    policy, pre, post = load(exports["pusht"])
    frames = store_frames(exports["workspace"], 2)
    pose = frames["state"][:, 2:5].astype(np.float64)
    corners = keypoints_from_pose(pose, GYM_PUSHT_CORNERS).reshape(2, 16)
    noise = torch.randn(1, 16, 2, generator=torch.Generator().manual_seed(3))
    policy.reset()
    batch = {"observation.environment_state": torch.tensor(corners, dtype=torch.float32)[None],
             "observation.state": torch.tensor(frames["state"][:, :2])[None]}  # (1, To, ...)
    got = post(policy.predict_action_chunk(pre(batch), noise=noise))
    sefa = Policy.load(exports["workspace"] / "distill", device="cpu")
    obs = {"keypoint": keypoints_from_pose(pose, LOCAL_KEYPOINTS).astype(np.float32),
           "state": frames["state"]}
    want = sefa.predict_action(obs, noise=noise).action
    scale = sefa.normalizer.params["action"].scale
    assert got.shape == want.shape == (1, 8, 2)
    # float32 corners of ~500 px through the affine weights: well within 1e-4 of the range
    assert float(((got - want).abs().numpy() * np.abs(scale)).max()) < 1e-4


def test_select_action_executes_receding_horizon_then_replans(exports):
    """Steps 0..7 are the first chunk's rows, predicted from the first frame padded to To
    frames; step 8 starts a chunk predicted from frames 7 and 8."""
    policy, pre, post = load(exports["state"])
    frames = store_frames(exports["workspace"])["state"][:, :2]
    policy.reset()
    actions = [post(policy.select_action(pre({"observation.state": torch.tensor(f)[None]})))
               for f in frames[:9]]
    ref, _, _ = load(exports["state"])  # the same noise_seed: the same noise draws
    ref.reset()
    first = ref.predict_action_chunk({"observation.state": torch.tensor(frames[[0, 0]])[None]})
    second = ref.predict_action_chunk({"observation.state": torch.tensor(frames[[7, 8]])[None]})
    np.testing.assert_allclose(torch.cat(actions[:8]).numpy(), first[0].numpy(), atol=1e-5)
    np.testing.assert_allclose(actions[8].numpy(), second[0, :1].numpy(), atol=1e-5)


def test_ensemble_execution_averages_overlapping_chunks_with_acts_weights(exports):
    """--policy.execution.mode=ensemble, replan_every 1, k = 0.5: step 1's action is the
    exp(-k i)-weighted mean of chunk 0's row 1 and chunk 1's row 0 (ACT's weights)."""
    policy, pre, post = load(exports["state"], {"execution.mode": "ensemble",
                                                "execution.ensemble_k": 0.5})
    assert policy.config.execution.mode == "ensemble"
    frames = store_frames(exports["workspace"])["state"][:, :2]
    policy.reset()
    actions = [post(policy.select_action(pre({"observation.state": torch.tensor(f)[None]})))
               for f in frames[:2]]
    ref, _, _ = load(exports["state"])
    ref.reset()
    c0 = ref.predict_action_chunk({"observation.state": torch.tensor(frames[[0, 0]])[None]})[0]
    c1 = ref.predict_action_chunk({"observation.state": torch.tensor(frames[[0, 1]])[None]})[0]
    w = np.exp(-0.5 * np.arange(2))
    w /= w.sum()
    np.testing.assert_allclose(actions[0][0].numpy(), c0[0].numpy(), atol=1e-5)
    np.testing.assert_allclose(actions[1][0].numpy(), w[0] * c0[1].numpy() + w[1] * c1[0].numpy(),
                               atol=1e-5)


def test_a_batch_of_environments_runs_one_executor_each(exports):
    """lerobot-eval steps B environments together: environment i's actions are those of a
    policy run on it alone with noise_seed + i."""
    policy, pre, post = load(exports["state"])
    frames = store_frames(exports["workspace"])["state"][:, :2]
    other = frames[::-1].copy()
    policy.reset()
    both = [post(policy.select_action(pre({"observation.state": torch.tensor(np.stack([a, b]))})))
            for a, b in zip(frames[:10], other[:10])]
    for i, env in enumerate((frames, other)):
        alone, _, _ = load(exports["state"], {"noise_seed": i})
        alone.reset()
        want = [alone.select_action({"observation.state": torch.tensor(f)[None]}) for f in env[:10]]
        np.testing.assert_allclose(torch.stack([b[i] for b in both]).numpy(),
                                   torch.cat(want).numpy(), atol=1e-5)


def test_coherent_execution_keeps_one_of_its_samples(exports):
    """--policy.execution.mode=coherent with 4 samples and a replan every 2 steps: each
    decision's chunk is one of the 4 the policy draws in one batched call."""
    policy, pre, post = load(exports["state"], {"execution.mode": "coherent",
                                                "execution.samples": 4,
                                                "execution.replan_every": 2})
    frames = store_frames(exports["workspace"])["state"][:, :2]
    policy.reset()
    actions = [post(policy.select_action(pre({"observation.state": torch.tensor(f)[None]})))[0]
               for f in frames[:4]]
    ref, _, _ = load(exports["state"])
    history = torch.tensor(frames[[0, 0]])[None].repeat(4, 1, 1)
    noise = torch.randn((4, 16, 2), generator=torch.Generator().manual_seed(0))  # seed 0 + env 0
    with torch.no_grad():
        samples = ref.chunk_model({"observation.state": history}, noise)[:, 1:3]  # steps 0, 1
    got = torch.stack(actions[:2])
    assert min(float((got - s).abs().max()) for s in samples) < 1e-5


@pytest.mark.parametrize("overrides, line", [
    ({"execution.replan_every": 9}, r"--policy.execution.replan_every: 9 is outside 1..8"),
    ({"execution.mode": "bid"}, r"--policy.execution.mode: bid contrasts the policy with a weaker"),
    ({"execution.mode": "receding", "execution.samples": 4},
     r"--policy.execution.samples: 4 samples need the coherent or bid mode"),
    ({"n_action_steps": 20}, r"--policy.n_action_steps: 20 steps from the current frame on "
                             r"need a chunk of 21, and the policy predicts horizon = 16 from "
                             r"n_obs_steps = 2 frames back \(at most 15\)"),
    ({"n_action_steps": 0}, r"--policy.n_action_steps: 0 steps: a chunk executes at least 1"),
])
def test_execution_settings_out_of_range_are_one_line(exports, overrides, line):
    with pytest.raises(ValueError, match=line) as err:
        load(exports["state"], overrides)
    assert "\n" not in str(err.value)


def test_training_inside_lerobot_says_to_train_with_sefa(exports):
    policy, _, _ = load(exports["state"])
    with pytest.raises(NotImplementedError, match="trained with sefa"):
        policy.forward({})


def test_a_folder_missing_a_file_is_one_line_naming_it(exports, tmp_path):
    folder = tmp_path / "broken"
    shutil.copytree(exports["pusht"], folder)
    (folder / "policy_preprocessor.json").unlink()
    cfg = PreTrainedConfig.from_pretrained(folder)
    with pytest.raises(Exception) as err:
        get_policy_class("sefa").from_pretrained(folder, config=cfg)
    line = str(err.value)
    assert "\n" not in line and "policy_preprocessor.json: missing" in line


def test_weights_of_another_network_are_one_line(exports, tmp_path):
    folder = tmp_path / "other"
    shutil.copytree(exports["pusht"], folder)
    shutil.copy(exports["state"] / "model.safetensors", folder / "model.safetensors")
    cfg = PreTrainedConfig.from_pretrained(folder)
    with pytest.raises(Exception, match=r"model.safetensors: .*(do not match|arrays do not match)") as err:
        get_policy_class("sefa").from_pretrained(folder, config=cfg)
    assert "\n" not in str(err.value)


def test_an_observation_without_the_policys_feature_is_one_line(exports):
    policy, pre, _ = load(exports["pusht"])
    policy.reset()
    with pytest.raises(KeyError, match="no 'observation.environment_state'"):
        policy.select_action(pre({"observation.state": torch.zeros(1, 2)}))


def test_the_plugin_imports_no_simulator_ros_reader_or_workspace_code():
    """What LeRobot imports for the policy: sefa's model code, not sefa_sim (gym-pusht,
    robosuite), the ROS and HDF5 readers, the workspace or the CLI."""
    code = ("import sys, lerobot_policy_sefa, lerobot_policy_sefa.modeling_sefa, "
            "lerobot_policy_sefa.processor_sefa, lerobot_policy_sefa.policy_server\n"
            "print(' '.join(sorted({m.split('.')[0] for m in sys.modules})))")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=300, cwd="/")
    assert run.returncode == 0, run.stderr
    loaded = set(run.stdout.split())
    assert {"sefa_model", "sefa_deploy", "torch"} <= loaded
    assert not loaded & {"sefa_sim", "sefa_pipelines", "sefa_cli", "rosbags", "mcap", "h5py",
                         "gym_pusht", "robosuite", "metaworld"}


def test_lerobot_outside_the_tested_versions_registers_nothing_and_says_so_in_one_line():
    """A LeRobot 0.7 (faked: importlib.metadata answers 0.7.0): one line on stderr, no type."""
    code = ("import importlib.metadata as m; real = m.version\n"
            "m.version = lambda n: '0.7.0' if n == 'lerobot' else real(n)\n"
            "import lerobot_policy_sefa as p; print(p.__all__)\n"
            "from lerobot.configs.policies import PreTrainedConfig\n"
            "print('sefa' in PreTrainedConfig.get_known_choices())")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert run.stdout.split() == ["[]", "False"]
    lines = [ln for ln in run.stderr.splitlines() if "lerobot_policy_sefa" in ln]
    assert len(lines) == 1 and "LeRobot 0.7.0 is outside" in lines[0] and ">=0.6.1,<0.7" in lines[0]


def test_the_export_saved_again_by_lerobot_loads_to_the_same_actions(exports, tmp_path):
    """LeRobot's save_pretrained (as lerobot-train's checkpoints) writes the folder it reads."""
    policy, pre, post = load(exports["state"])
    policy.save_pretrained(tmp_path / "again")
    pre.save_pretrained(tmp_path / "again")
    post.save_pretrained(tmp_path / "again")
    again, _, _ = load(tmp_path / "again")
    batch = {"observation.state": torch.tensor([[[250.0, 300.0], [251.0, 301.0]]])}
    noise = torch.randn(1, 16, 2)
    assert torch.equal(policy.predict_action_chunk(batch, noise=noise),
                       again.predict_action_chunk(batch, noise=noise))
    assert json.loads((tmp_path / "again" / "config.json").read_text())["type"] == "sefa"
