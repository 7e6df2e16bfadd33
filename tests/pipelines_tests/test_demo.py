"""The built-in default (`sefa demo`): its pipeline at a tiny size from scripted Meta-World
demonstrations to its table, the table's words from its numbers, and its output holding only
sefa's lines; and the built-in ROS recording, a ROS 2 MCAP bag written by a scripted expert,
ingested with its topic map."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from sefa_data.errors import SefaInputError
from sefa_data.ingest import IngestOptions, ingest
from sefa_data.store.zarr_store import EpisodeStore
from sefa_pipelines.builtin_demo import (TOPIC_MAP, demo_pipeline, findings, record_reach_bag,
                                         run_demo)
from sefa_pipelines.stages import load_pipeline

REPO = Path(__file__).resolve().parents[2]
PRESETS = REPO / "pipelines"


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
    # the Meta-World preset's sizes (docs/results.md's Meta-World study): the demo's table
    # reproduces that study's button-press row
    preset = load_pipeline(Path("/nonexistent"), PRESETS / "metaworld.yaml")
    assert (cfg.reflow, cfg.align, cfg.distill) == (preset.reflow, preset.align, preset.distill)
    assert cfg.train_config == preset.train_config
    train = base_train_config(Path("."), cfg)  # the shipped train YAML resolves and validates
    assert list(train.shape_meta.obs) == ["observation.state_observation"]


TINY = ["policy.mlp_hidden_dims=[32,32]", "policy.time_embed_dim=16", "training.batch_size=32",
        "training.max_steps=20", "training.val_every=20", "training.checkpoint_every=20",
        "training.lr_warmup_steps=2"]
# the demo at a tiny size, in a child process: its output is what a user would see
DEMO = f"""
import json, sys
from pathlib import Path
from sefa_pipelines.builtin_demo import demo_pipeline, run_demo
cfg = demo_pipeline()
cfg.train = {TINY!r}
cfg.reflow.samples_per_window, cfg.reflow.max_windows, cfg.reflow.rtol = 2, 16, 1e-3
cfg.reflow.atol = 1e-3
# a base flow of 20 steps is far from the expert: the nearest 20 % is refused, a fixed eps is not
cfg.align.replace_fraction, cfg.align.eps = None, 1.0
cfg.distill.train_overrides = {TINY[3:]!r}
summary = run_demo(Path(sys.argv[1]), lambda line: print(line, file=sys.stderr), episodes=2,
                   n_test=1, pipeline=cfg)
print(json.dumps(summary["policy"]))
"""


@pytest.fixture(scope="module")
def tiny_demo(tmp_path_factory):
    pytest.importorskip("metaworld", reason="Meta-World is not installed (sefa[sim])")
    ws = tmp_path_factory.mktemp("demo") / "ws"
    runs = [subprocess.run([sys.executable, "-c", DEMO, str(ws)], capture_output=True, text=True,
                           cwd=REPO) for _ in range(2)]
    for r in runs:
        assert r.returncode == 0, r.stderr
    return ws, [json.loads(r.stdout) for r in runs], [r.stderr for r in runs]


def test_the_demo_compares_the_student_with_one_euler_step_under_both_executions(tiny_demo):
    ws, (summary, again), _ = tiny_demo
    rows = summary["rows"]
    student = rows[-1]["policy"]
    assert [(r["policy"], r["solver"], r["every"]) for r in rows] == [
        ("base flow, RK45", "rk45", 8), ("base flow, Euler-1", "euler-1", 8),
        ("base flow, Euler-1", "euler-1", 1), (student, "euler-1", 8), (student, "euler-1", 1)]
    assert rows[0]["nfe"] > 1 and [r["nfe"] for r in rows[1:]] == [1, 1, 1, 1]
    assert all(r["n_test"] == 1 and r["success_rate"] in (0.0, 1.0) for r in rows)
    assert all(r["latency_ms"] > 0 and r["val_action_mse"] > 0 for r in rows)
    assert summary["env"] == "Meta-World button-press" and summary["findings"]
    # the evaluations are kept as `sefa eval` keeps them: `sefa results` lists the five
    assert len(list((ws / "evals").glob("metaworld_button-press-*/eval_log.json"))) == 5
    # the second run answers from the caches, with the same table (the latency measured again)
    def table(s):
        return [{k: v for k, v in r.items() if k != "latency_ms"} for r in s["rows"]]
    assert table(again) == table(summary) and again["findings"][0] == summary["findings"][0]


def test_the_demo_prints_only_sefas_lines(tiny_demo):
    """No third party's start-up notes (robosuite's macro file, its models, mink, a controller
    file; Python warnings): every line is one of sefa's own."""
    _, _, (first, again) = tiny_demo
    for err in (first, again):
        assert "robosuite" not in err and "Warning" not in err and "warn(" not in err, err
    assert "collecting 2 scripted Meta-World button-press demonstrations" in first
    assert "evaluated (metaworld:button-press, receding K=1 (given)" in first
    assert "evaluated" not in again and "cached (metaworld:button-press" in again


def test_robosuites_start_up_notes_are_filtered_and_its_errors_kept():
    pytest.importorskip("robosuite", reason="robosuite is not installed (sefa[sim])")
    code = ("import sefa_sim, logging, robosuite\n"
            "from robosuite.utils.log_utils import ROBOSUITE_DEFAULT_LOGGER as log\n"
            "log.warning('a note'); log.error('an error')")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO)
    assert r.returncode == 0, r.stderr
    assert "[robosuite ERROR] an error" in r.stderr
    assert "macro file" not in r.stderr and "a note" not in r.stderr, r.stderr


def outcomes(successes: int, n: int = 50) -> list[list[float]]:
    """[seed, success] of n seeds, the first `successes` of them succeeding."""
    return [[100000 + i, float(i < successes)] for i in range(n)]


def row(run: str, solver: str, every: int, successes: int, nfe: int, ms: float, name: str) -> dict:
    return {"run": run, "solver": solver, "every": every, "success_rate": successes / 50,
            "per_seed": outcomes(successes), "nfe": nfe, "latency_ms": ms, "policy": name}


ROWS = [  # the success rates of the Meta-World study's button-press row and its executions
    row("train", "rk45", 8, 47, 266, 185.1, "base flow, RK45"),
    row("train", "euler-1", 8, 34, 1, 0.67, "base flow, Euler-1"),
    row("train", "euler-1", 1, 44, 1, 0.67, "base flow, Euler-1"),
    row("distill", "euler-1", 8, 39, 1, 0.64, "SeFA one-step"),
    row("distill", "euler-1", 1, 50, 1, 0.64, "SeFA one-step"),
]


def test_the_tables_words_come_from_its_numbers():
    """Paired over the seeds: the student succeeds where one Euler step did and on 5 seeds
    more (8 actions a prediction), 6 more (every step); the standard errors worked by hand:
    sqrt((5 x 0.9^2 + 45 x 0.1^2) / 49 / 50) = 0.043, sqrt((6 x 0.88^2 + 44 x 0.12^2) / 49 /
    50) = 0.046."""
    assert findings(ROWS) == [
        "The SeFA one-step student against one Euler step of its base flow, at the same cost (one "
        "network evaluation a prediction), paired over the same seeds (± the standard error): 78% "
        "against 68% (+10 ± 4 points) with 8 actions a prediction, 100% against 88% (+12 ± 5 "
        "points) predicting at every step.",
        "The base flow solved accurately (RK45, 266 network evaluations) succeeds in 94% at 185 ms "
        "a prediction: too slow to predict at every step of Meta-World's 12.5 ms control period."]
    # a student that does worse says so in the same words: 4 seeds lost, none won
    worse = [row("distill", "euler-1", 8, 30, 1, 0.64, "SeFA one-step") if r["run"] == "distill"
             and r["every"] == 8 else r for r in ROWS]
    assert "60% against 68% (-8 ± 4 points) with 8 actions" in findings(worse)[0]


def test_a_workspace_of_other_data_is_refused(tmp_path):
    (tmp_path / "sefa.yaml").write_text("train: []\n")
    with pytest.raises(SefaInputError, match="not this demo's .it has a sefa.yaml but no "
                                             "recordings/button-press.hdf5."):
        run_demo(tmp_path)


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

