"""The presets shipped with sefa, named from any folder (issue 46): `sefa presets` lists them,
`sefa train --preset NAME` and `sefa run --preset NAME` take them outside a sefa checkout, and a
path to a preset file that is not there (the older hint `sefa train
pipelines/lerobot_camera_cpu_train.yaml`, run elsewhere) names the preset. The wheel carries
the files (tests/test_packaging.py); here the commands run in a folder that is no checkout.
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest
import yaml

from cli_inprocess import run_cli

REPO = Path(__file__).resolve().parents[2]
SMALL = ["training.max_steps=2", "training.batch_size=16", "training.val_every=2",
         "training.checkpoint_every=2", "training.val_batches=1", "training.val_sample_windows=4",
         "training.lr_warmup_steps=1", "flow.solver=euler", "flow.steps=2"]


def sefa(cwd: Path, *args) -> subprocess.CompletedProcess:
    return run_cli(*args, cwd=cwd, threads=1)


def one_error(r: subprocess.CompletedProcess) -> str:
    errors = [ln for ln in r.stderr.splitlines() if ln.startswith("error: ")]
    assert r.returncode == 1 and len(errors) == 1 and "Traceback" not in r.stderr, r.stderr
    return errors[0]


def test_presets_lists_each_name_with_what_it_is_for_and_its_files(tmp_path):
    r = sefa(tmp_path, "presets", "--json")
    assert r.returncode == 0, r.stderr
    rows = {row["name"]: row for row in json.loads(r.stdout)}
    camera = rows["lerobot_camera_cpu"]
    assert camera["for"] == ("any LeRobot camera dataset: cameras at 64x64, the tiny encoder, "
                             "for a CPU")
    assert Path(camera["run"]).name == "lerobot_camera_cpu.yaml"
    assert Path(camera["train"]).name == "lerobot_camera_cpu_train.yaml"
    assert rows["lift_lowdim"]["run"] is None  # a train config alone
    assert Path(rows["builtin_default"]["train"]).name == "metaworld_train.yaml"  # the demo
    for row in rows.values():  # every one says what it is for, and its files are there
        assert row["for"] and all(Path(f).is_file() for f in (row["run"], row["train"]) if f)
    shipped = {p.name for p in (REPO / "pipelines").glob("*.yaml")}
    listed = {Path(f).name for row in rows.values() for f in (row["run"], row["train"]) if f}
    assert listed == shipped  # no file left unnamed
    r = sefa(tmp_path, "presets")
    assert r.returncode == 0 and "lerobot_camera_cpu" in r.stdout


@pytest.fixture(scope="module")
def store(shared_data, tmp_path_factory) -> Path:
    """The Push-T low-dim store the pusht_lowdim preset is for."""
    ws = tmp_path_factory.mktemp("store")
    r = run_cli("ingest", shared_data / "pusht_cchi_v7_replay.zarr", "--fps", "10", "--key",
                "keypoint", "--key", "state", "--key", "action", "-w", ws, cwd=ws)
    assert r.returncode == 0, r.stderr
    return ws / "dataset.zarr"


def test_train_and_run_take_a_preset_by_name_outside_a_checkout(store, tmp_path):
    ws = tmp_path / "ws"
    ws.mkdir()
    shutil.copytree(store, ws / "dataset.zarr")
    r = sefa(tmp_path, "train", "--preset", "pusht_lowdim", *SMALL, "-w", ws)
    assert r.returncode == 0, r.stderr[-3000:]
    config = json.loads((ws / "train/checkpoints/latest/config.json").read_text())["train_config"]
    preset = yaml.safe_load((REPO / "pipelines/pusht_lowdim_train.yaml").read_text())
    assert config["policy"]["mlp_hidden_dims"] == preset["policy"]["mlp_hidden_dims"]
    assert config["shape_meta"]["obs_keys"] == ["keypoint", "state"]
    # the pipeline of the same name becomes the workspace's sefa.yaml (here: a fresh one)
    other = tmp_path / "other"
    other.mkdir()
    shutil.copytree(store, other / "dataset.zarr")
    r = sefa(tmp_path, "run", "--preset", "nope", "-w", other)
    assert one_error(r).startswith("error: --preset: no preset 'nope' (presets: builtin_default, "
                                   "lerobot_camera_cpu, lift_lowdim,")
    r = sefa(tmp_path, "run", "--preset", "lift_lowdim", "-w", other)
    assert "'lift_lowdim' is a train config, not a pipeline: `sefa train --preset lift_lowdim`" \
        in one_error(r)
    r = sefa(tmp_path, "train", "some.yaml", "--preset", "pusht_lowdim", "-w", other)
    assert one_error(r) == "error: --preset: give a config file or --preset, not both"
    assert not (other / "sefa.yaml").exists() and not (other / "runs").exists()


def test_a_preset_path_outside_a_checkout_names_the_preset(tmp_path):
    """The hint `sefa train pipelines/lerobot_camera_cpu_train.yaml` (and the docs) named a path
    that exists only in a sefa checkout."""
    r = sefa(tmp_path, "train", "pipelines/lerobot_camera_cpu_train.yaml", "-w", tmp_path)
    assert one_error(r) == (
        "error: pipelines/lerobot_camera_cpu_train.yaml: file not found; the installed preset "
        "of that name: `sefa train --preset lerobot_camera_cpu`")
    r = sefa(tmp_path, "run", "pipelines/pusht_lowdim.yaml", "-w", tmp_path)
    assert one_error(r) == ("error: pipelines/pusht_lowdim.yaml: no such pipeline file; the "
                            "installed preset of that name: `sefa run --preset pusht_lowdim`")


def test_the_training_hint_names_a_preset_that_works_anywhere():
    """The cost line's advice for a long camera run on a CPU is a command that works in any
    folder."""
    from sefa_model.train.loop import CAMERA_PRESET

    assert CAMERA_PRESET == "--preset lerobot_camera_cpu"
    from sefa_pipelines.presets import resolve

    assert resolve("lerobot_camera_cpu", "train").name == "lerobot_camera_cpu_train.yaml"


# presets meant for more than one task or robot align by a fraction of the couplings (`--eps
# auto`): a fixed eps is in normalized action units, whose distances differ by task (eps 0.05
# replaced 99.4 % of Meta-World reach's couplings, none of push-wall's, none on a robot arm's
# recording). The Push-T presets keep the eps measured on Push-T (docs/results.md's sweep).
ANY_TASK = ("builtin_default", "lerobot_camera_cpu", "metaworld")


@pytest.mark.parametrize("name", ANY_TASK)
def test_a_preset_for_many_tasks_aligns_by_a_fraction_not_a_fixed_eps(name):
    from sefa_model.sefa.alignment import AUTO_FRACTION
    from sefa_pipelines.presets import resolve
    from sefa_pipelines.stages import load_pipeline

    cfg = load_pipeline(Path("/nonexistent"), resolve(name, "run"))
    assert cfg.align.replace_fraction == AUTO_FRACTION and cfg.distill.align


def test_the_metaworld_preset_is_what_its_comments_and_the_docs_say():
    """Horizon 16, 2 observations, 8 actions executed (SeFA's reference configs; 3D Diffusion
    Policy's dp3.yaml has 4 and 3, and the comment says so), and of 10 demonstrations the one
    held out for validation is the one 3D Diffusion Policy's code holds out: its get_val_mask
    (val_ratio 0.02, at least one episode, seed 42), written out here, against the store's."""
    import numpy as np

    from sefa_data.store.zarr_store import split_masks
    from sefa_pipelines.presets import resolve
    from sefa_pipelines.stages import base_train_config, load_pipeline

    train = base_train_config(Path("."), load_pipeline(Path("."), resolve("metaworld", "run")))
    p = train.policy
    assert (p.horizon, p.n_obs_steps, p.n_action_steps) == (16, 2, 8)
    text = (REPO / "pipelines/metaworld_train.yaml").read_text()
    assert "3D Diffusion Policy predicts horizon 4\n# and executes 3" in text

    def dp3_val_mask(n_episodes, val_ratio=0.02, seed=42):  # DP3's common/sampler.py
        mask = np.zeros(n_episodes, dtype=bool)
        n_val = min(max(1, round(n_episodes * val_ratio)), n_episodes - 1)
        mask[np.random.default_rng(seed=seed).choice(n_episodes, size=n_val, replace=False)] = True
        return mask

    train_mask, valid = split_masks(10, 0.1, 42)  # what `sefa ingest` records for 10 episodes
    assert train_mask.sum() == 9 and (valid == dp3_val_mask(10)).all()
    docs = " ".join((REPO / "docs/metaworld.md").read_text().split())
    assert "9 of them are trained on" in docs and "horizon 4" in docs
    assert "replaces the nearest 20 %" in docs
