"""Image policies in closed loop on Push-T (issue 14): `evaluate_pusht` renders the camera frames
a policy with an `img` key needs, and its rollouts are deterministic per seed.

The store is the first three real Push-T episodes with their images (../shared/data); the
policy is a tiny image flow trained for 4 steps, so only the plumbing is scored, not skill."""

from __future__ import annotations

import json

import pytest

pytest.importorskip("gym_pusht", reason="gym-pusht (the sim extra) is not installed")

from conftest import TINY_IMAGE_TRAIN  # noqa: E402
from sefa_data.errors import SefaInputError  # noqa: E402
from sefa_model.policy.checkpoint import write_checksums  # noqa: E402
from sefa_model.config import load_train_config  # noqa: E402
from sefa_model.train.loop import train  # noqa: E402
from sefa_sim.rollouts import evaluate_pusht  # noqa: E402

TINY_IMAGE = TINY_IMAGE_TRAIN


@pytest.fixture(scope="module")
def image_policy(shared_data, tmp_path_factory):
    from conftest import pusht_image_store

    tmp = tmp_path_factory.mktemp("image_rollouts")
    store = pusht_image_store(shared_data, tmp)
    train(load_train_config(None, TINY_IMAGE), tmp / "run", store)
    return tmp / "run" / "checkpoints" / "latest"


def test_image_policy_rollouts_are_deterministic_per_seed(image_policy, tmp_path):
    first = evaluate_pusht(image_policy, n_test=2, max_steps=24, out=tmp_path / "a", device="cpu")
    again = evaluate_pusht(image_policy, n_test=2, max_steps=24, out=tmp_path / "b", device="cpu")
    assert [r["seed"] for r in first["per_seed"]] == [100000, 100001]
    assert first["per_seed"] == again["per_seed"]
    assert all(r["steps"] == 24 for r in first["per_seed"])
    log = json.loads((tmp_path / "a" / "eval_log.json").read_text())
    assert log["per_seed"] == first["per_seed"] and log["kind"] == "base_flow"


def test_the_policy_gets_the_rendered_camera_frames(image_policy, monkeypatch):
    from sefa_model.policy.artifact import Policy
    from sefa_sim.pusht import PushTEnv

    seen = []
    real = Policy.predict_action
    # the executor asks for its samples as a batch (of one here)
    monkeypatch.setattr(Policy, "predict_action", lambda self, obs, **kw: seen.append(
        {k: v[0] for k, v in obs.items()}) or real(self, obs, **kw))
    evaluate_pusht(image_policy, n_test=1, max_steps=16, device="cpu")
    assert len(seen) == 2  # two chunks of 8 actions
    env = PushTEnv()
    for obs in seen:
        assert obs["img"].shape == (2, 96, 96, 3) and obs["img"].dtype.name == "uint8"
        env.set_state(obs["state"][-1])
        assert (obs["img"][-1] == env.image()).all()
    env.reset(100000)
    assert (seen[0]["img"][0] == env.image()).all()  # the scene of seed 100000


def test_a_policy_needing_an_unknown_camera_is_refused_by_name(image_policy, tmp_path):
    import shutil

    moved = tmp_path / "ckpt"
    shutil.copytree(image_policy, moved)
    meta = json.loads((moved / "config.json").read_text())
    obs = meta["train_config"]["shape_meta"]["obs"]
    obs["wrist_cam"] = obs.pop("img")
    (moved / "config.json").write_text(json.dumps(meta))
    write_checksums(moved)  # consistent checksums: the camera check must catch it
    with pytest.raises(SefaInputError, match="wrist_cam"):
        evaluate_pusht(moved, n_test=1, max_steps=8, device="cpu")


@pytest.fixture(scope="module")
def lerobot_named_policy(shared_data, tmp_path_factory):
    """The same three real episodes under LeRobot's Push-T names (written with zarr):
    `observation.image` the camera, `observation.state` the agent's position (state[:, :2]),
    trained as `image_policy` is."""
    import zarr

    from sefa_data.ingest import IngestOptions, ingest

    tmp = tmp_path_factory.mktemp("lerobot_named")
    src = zarr.open_group(str(shared_data / "pusht_cchi_v7_replay.zarr"), mode="r")
    ends = src["meta/episode_ends"][:3]
    root = zarr.open_group(str(tmp / "small.zarr"), mode="w", zarr_format=2)
    root.create_array("data/observation.image", data=src["data"]["img"][: ends[-1]])
    root.create_array("data/observation.state", data=src["data"]["state"][: ends[-1], :2])
    root.create_array("data/action", data=src["data"]["action"][: ends[-1]])
    root.create_array("meta/episode_ends", data=ends)
    ingest([tmp / "small.zarr"], tmp / "store.zarr", IngestOptions(fps=10))
    overrides = [o for o in TINY_IMAGE if not o.startswith("shape_meta.")]
    train(load_train_config(None, overrides), tmp / "run", tmp / "store.zarr")
    return tmp / "run" / "checkpoints" / "latest"


def test_lerobot_push_t_names_are_fed_by_the_simulator(image_policy, lerobot_named_policy):
    """LeRobot's names are recognised (and said); the policy sees what the `img`/`state`
    policy sees, so both score the same per seed; an explicit --key-map gives the same."""
    said = []
    got = evaluate_pusht(lerobot_named_policy, n_test=2, max_steps=16, device="cpu", log=said.append)
    assert said == ["Push-T's img as observation.image, agent_pos as observation.state "
                    "(LeRobot's names)"]
    want = evaluate_pusht(image_policy, n_test=2, max_steps=16, device="cpu")
    assert got["per_seed"] == want["per_seed"]
    assert got["key_map"] == {"img": "observation.image", "agent_pos": "observation.state"}
    mapped = evaluate_pusht(lerobot_named_policy, n_test=2, max_steps=16, device="cpu",
                            key_map={"img": "observation.image", "agent_pos": "observation.state"})
    assert mapped["per_seed"] == got["per_seed"]


def test_an_unfed_policy_key_says_how_to_map_it(lerobot_named_policy):
    with pytest.raises(SefaInputError) as e:  # the image mapped, the state left unfed
        evaluate_pusht(lerobot_named_policy, n_test=1, max_steps=8, device="cpu",
                       key_map={"img": "observation.image"})
    assert "nothing feeds the policy's observation.state" in e.value.line()
    assert "--key-map agent_pos=observation.state" in e.value.line()
    with pytest.raises(SefaInputError, match="Push-T has no observation 'pixels'"):
        evaluate_pusht(lerobot_named_policy, n_test=1, max_steps=8, device="cpu",
                       key_map={"pixels": "observation.image"})
