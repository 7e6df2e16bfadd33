"""The built-in default's recording: a ROS 2 MCAP bag written by the scripted expert, ingested
with its topic map (the full `sefa demo` pipeline is exercised stage by stage elsewhere)."""

from pathlib import Path

import numpy as np

from sefa_pipelines.builtin_demo import TOPIC_MAP, demo_pipeline, record_reach_bag
from sefa_data.ingest import IngestOptions, ingest
from sefa_data.store.zarr_store import EpisodeStore


def test_builtin_recording_ingests_into_six_episodes(tmp_path):
    bag = record_reach_bag(tmp_path / "reach", episodes=6, seconds=4.0, seed=0)
    (tmp_path / "map.yaml").write_text(TOPIC_MAP)
    ingest([bag], tmp_path / "s.zarr", IngestOptions(topic_map=str(tmp_path / "map.yaml")))
    store = EpisodeStore.open(tmp_path / "s.zarr")
    assert store.n_episodes == 6 and store.episode_lengths.tolist() == [40] * 6
    ep = store.get_episode(0)
    assert set(ep) == {"action", "observation.state", "observation.target"}
    # the expert drives the arm towards the target: the gap closes over the episode
    gap = np.abs(ep["observation.target"][:, :2] - ep["observation.state"])
    assert gap[-1].max() < 0.5 * gap[0].max()
    # commands are clipped proportional control, 2 * (goal - q), held between 50 Hz messages
    assert np.abs(ep["action"]).max() <= 1.5 + 1e-6
    assert store.attrs["stats"]["observation.target"]["constant"] == [False, False, True]


def test_demo_pipeline_settings_are_valid():
    from sefa_pipelines.stages import base_train_config

    cfg = demo_pipeline()
    # alignment must replace something, whatever the couplings' distances: the demo's student
    # is then SeFA's, not plain reflow (a fixed eps 0.05 replaced 0 of its 10,000 couplings)
    assert cfg.reflow.iters == 1 and cfg.align.replace_fraction == 0.2 and cfg.distill.align
    train = base_train_config(Path("."), cfg)  # the shipped train YAML resolves and validates
    assert "observation.cube_pos" in train.shape_meta.obs and train.policy.head == "mlp"


def test_presets_load():
    from pathlib import Path

    from sefa_pipelines.stages import base_train_config, load_pipeline

    presets = Path(__file__).resolve().parents[2] / "pipelines"
    for name in ("builtin_default.yaml", "pusht_lowdim.yaml", "pusht_lowdim_full.yaml"):
        cfg = load_pipeline(Path("/nonexistent"), presets / name)
        assert cfg.align.eps == 0.05 or cfg.align.replace_fraction == 0.2
        # a preset's train config is the file shipped beside it, whatever the working directory
        assert Path(cfg.train_config).is_absolute() and Path(cfg.train_config).parent == presets
        train = base_train_config(Path("."), cfg)
        assert train.objective == "flow" and train.training.max_steps > 0
    full = base_train_config(Path("."), load_pipeline(Path("."), presets / "pusht_lowdim_full.yaml"))
    assert (full.policy.head, full.training.lr, full.training.batch_size) == ("unet", 1e-4, 256)


def test_every_yaml_under_pipelines_loads():
    """Each shipped YAML resolves with its loader: a train config (`*_train*.yaml`, given to `sefa
    train` or named by a preset's train_config) with the train config loader, the others as
    pipeline presets."""
    from sefa_model.config import load_train_config
    from sefa_pipelines.stages import base_train_config, load_pipeline, reflowed_flow_config, student_config

    presets = Path(__file__).resolve().parents[2] / "pipelines"
    files = sorted(presets.glob("*.yaml"))
    train_files = [p for p in files if "_train" in p.stem]
    assert {"pusht_image_train.yaml", "pusht_image_train_full.yaml"} <= {p.name for p in train_files}
    for path in files:
        if path in train_files:
            cfg = load_train_config(path)
        else:
            pipe = load_pipeline(Path("/nonexistent"), path)
            cfg = base_train_config(Path("."), pipe)
            # each stage's overrides apply on top of it (strict keys)
            reflowed_flow_config(cfg, pipe.reflow.train_overrides)
            student_config(cfg, pipe.distill.train_overrides)
        assert cfg.training.max_steps > 0, path.name

    # Diffusion Policy's CNN image policy on Push-T (image_pusht_diffusion_policy_cnn.yaml)
    full = load_train_config(presets / "pusht_image_train_full.yaml")
    p = full.policy
    assert (p.image_encoder, p.image_pool, p.image_feature_dim, p.crop_shape) == (
        "resnet18", "spatial_softmax", 64, [84, 84])
    assert (p.horizon, p.n_obs_steps, p.n_action_steps, p.down_dims, p.time_embed_dim) == (
        16, 2, 8, [512, 1024, 2048], 128)
    assert (full.training.batch_size, full.training.lr, full.training.max_steps) == (64, 1e-4, 3050 * 340)
    assert full.shape_meta.obs["img"].type == "rgb" and full.shape_meta.obs["state"].dims == [0, 2]
    cpu = load_train_config(presets / "pusht_image_train.yaml")
    assert (cpu.policy.image_encoder, cpu.policy.crop_shape, cpu.training.batch_size) == (
        "tiny", [84, 84], 64)


def test_a_student_is_named_by_what_ran():
    """The demo's table (and every table) names the student from its distill record: SeFA only
    when alignment replaced something; the method when it is not the reference's."""
    from sefa_pipelines.report import student_label

    aligned = {"kind": "sefa_one_step", "alignment": {"n_replaced": 2000, "eps": 0.01}}
    assert student_label(aligned) == "SeFA one-step"
    assert student_label({**aligned, "method": "rfpp"}) == "SeFA one-step, rfpp"
    nothing = {"kind": "reflow_one_step", "alignment": {"n_replaced": 0, "eps": 0.05}}
    assert student_label(nothing) == "reflow one-step (alignment replaced nothing)"
    assert student_label({"kind": "reflow_one_step", "alignment": None}) == "reflow one-step (no alignment)"
    assert student_label({"kind": "one_step", "method": "mean_flow"}).startswith("one-step (mean flow")

