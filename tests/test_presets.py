"""Every preset shipped in pipelines/ loads with the strict config loaders: a pipeline preset,
its train config (named beside it), and each stage's overrides on top of it."""
from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from pipelines.stages import base_train_config, load_pipeline, reflowed_flow_config, student_config
from sefa_model.config import load_train_config

PRESETS = Path(__file__).resolve().parents[1] / "pipelines"
PIPELINES = sorted(p for p in PRESETS.glob("*.yaml") if "train_config" in (yaml.safe_load(p.read_text()) or {}))
TRAIN = sorted(p for p in PRESETS.glob("*.yaml") if p not in PIPELINES)


@pytest.mark.parametrize("path", PIPELINES, ids=lambda p: p.name)
def test_pipeline_preset_loads_with_its_train_config(path, tmp_path):
    cfg = load_pipeline(tmp_path, path)
    assert Path(cfg.train_config).is_file(), f"{path.name} names a missing {cfg.train_config}"
    base = base_train_config(tmp_path, cfg)
    reflowed_flow_config(base, cfg.reflow.train_overrides)
    student_config(base, cfg.distill.train_overrides)


@pytest.mark.parametrize("path", TRAIN, ids=lambda p: p.name)
def test_train_preset_loads(path):
    load_train_config(path)


def test_image_presets_are_diffusion_policys_task():
    for name in ("pusht_image_train.yaml", "pusht_image_train_full.yaml"):
        path = PRESETS / name
        if not path.exists():
            pytest.skip(f"{name} not shipped yet")
        cfg = load_train_config(path)
        obs = cfg.shape_meta.obs
        assert obs["img"].type == "rgb" and obs["state"].dims == [0, 2]
        assert cfg.policy.n_obs_steps == 2 and cfg.policy.crop_shape == [84, 84]
