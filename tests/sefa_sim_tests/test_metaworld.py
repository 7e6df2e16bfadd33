"""Meta-World (metaworld 3.1.1): the scripted demonstrations `sefa collect --env metaworld:TASK`
records, the goal each seed fixes, the difficulty groups, closed-loop evaluation after a tiny
SeFA pipeline on two tasks, and the one-line answer to an unknown task or group.

Every file here is written by the real collector (Meta-World's own envs and scripted policies,
written with h5py); the CLI runs in-process (tests/sefa_inprocess.py). A Meta-World episode takes
about half a second on 2 cores, most of it building the env.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import sefa_sim  # noqa: F401  (sets MUJOCO_GL before mujoco loads)

h5py = pytest.importorskip("h5py")
try:
    import metaworld  # noqa: F401
except (ImportError, OSError) as e:  # OSError: mujoco's shared library fails to load
    pytest.skip(f"metaworld cannot be imported ({type(e).__name__}: {e}); "
                "install the sim extra: pip install -e '.[sim]'", allow_module_level=True)

from sefa_inprocess import sefa
from sefa_sim.metaworld import (CONTROL_FREQ, GROUPS, OBS_KEYS, PARTS, STATE_KEY, TASKS,
                                collect_metaworld, make_env, resolve)

REPO = Path(__file__).resolve().parents[2]
EPISODES = 3
SEED = 7


@pytest.fixture(scope="module")
def collected(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict, Path]:
    root = tmp_path_factory.mktemp("metaworld")
    first, second = root / "a.hdf5", root / "b.hdf5"
    result = collect_metaworld(first, "reach", EPISODES, SEED)
    collect_metaworld(second, "reach-v3", EPISODES, SEED)  # Meta-World's own name works too
    return first, result, second


def test_every_seeded_scripted_episode_succeeds(collected) -> None:
    _, result, _ = collected
    assert result["task"] == "reach" and result["attempted"] == EPISODES
    assert result["successful"] == EPISODES, f"failed seeds: {result['failed_seeds']}"
    assert result["failed_seeds"] == [] and result["steps"] > 0


def test_file_has_robomimic_layout_with_metaworlds_named_parts(collected) -> None:
    path, result, _ = collected
    with h5py.File(path, "r") as f:
        data = f["data"]
        assert list(data) == [f"demo_{i}" for i in range(EPISODES)]
        for i, name in enumerate(data):
            demo = data[name]
            actions = demo["actions"][()]
            steps = len(actions)
            assert actions.shape == (steps, 4) and np.all(np.abs(actions) <= 1.0)
            assert set(demo["obs"]) == set(OBS_KEYS) == set(demo["next_obs"])
            state = demo["obs"][STATE_KEY][()]
            assert state.shape == (steps, 39)
            for key, part in PARTS.items():  # each part is its slice of the whole vector
                np.testing.assert_array_equal(demo["obs"][key][()], state[:, part], key)
            # Meta-World's frame stacking: entries 18:36 are the previous step's 0:18
            np.testing.assert_array_equal(state[1:, 18:36], state[:-1, :18])
            # the goal is fixed for the episode
            assert np.all(demo["obs"]["goal_pos"][()] == demo["obs"]["goal_pos"][0])
            np.testing.assert_array_equal(demo["next_obs"][STATE_KEY][:-1], state[1:])
            assert demo["dones"][()].tolist() == [0] * (steps - 1) + [1]
            assert demo["rewards"].shape == (steps,) and demo["states"].shape[0] == steps
            assert demo.attrs["seed"] == SEED + i and demo.attrs["num_samples"] == steps
        assert data.attrs["total"] == result["steps"]
        env_args = json.loads(data.attrs["env_args"])
        env_info = json.loads(data.attrs["env_info"])
    assert env_args["env_name"] == "Meta-World/goal_observable" and env_args["type"] == 2
    assert env_args["env_kwargs"]["env_name"] == "reach-v3"
    assert env_args["env_version"] == "3.1.1" and env_args["difficulty"] == "easy"
    env = make_env("reach", 0)
    assert env_info["control_freq"] == CONTROL_FREQ == 1 / env.dt  # what ingest takes as fps


def test_same_seed_gives_identical_demos(collected) -> None:
    first, _, second = collected
    with h5py.File(first, "r") as a, h5py.File(second, "r") as b:
        for name in a["data"]:
            for key in ("actions", "states", f"obs/{STATE_KEY}"):
                np.testing.assert_array_equal(a["data"][name][key][()], b["data"][name][key][()])


def test_a_seed_fixes_the_goal_as_metaworlds_mt1_benchmark_does() -> None:
    """Seed s gives the scene of the first task MT1(task, seed=s) draws, set through
    Meta-World's public API (set_task); two seeds give two goals."""
    import metaworld

    reference = metaworld.ALL_V3_ENVIRONMENTS["pick-place-v3"]()
    reference.set_task(metaworld.MT1("pick-place-v3", seed=3).train_tasks[0])
    expected, _ = reference.reset()
    ours, _ = make_env("pick-place", 3).reset()
    np.testing.assert_array_equal(ours, expected)
    # what the file's env_args names rebuilds the same scene
    import gymnasium as gym

    rebuilt, _ = gym.make("Meta-World/goal_observable", env_name="pick-place-v3", seed=3).reset()
    np.testing.assert_array_equal(rebuilt, expected)
    other, _ = make_env("pick-place", 4).reset()
    assert not np.array_equal(other[36:], ours[36:])


def test_failed_episodes_are_not_kept_and_their_seeds_are_reported(tmp_path: Path) -> None:
    from sefa_data.errors import SefaInputError

    # none succeeding writes nothing (a file without a demonstration is no recording)
    with pytest.raises(SefaInputError, match=r"none of the 2 episode\(s\) succeeded \(seeds 5, "
                                             r"6\): nothing written"):
        collect_metaworld(tmp_path / "short.hdf5", "pick-place", 2, seed=5, max_steps=3)
    assert not (tmp_path / "short.hdf5").exists()


def test_robomimic_sequence_dataset_reads_the_file_with_its_defaults(collected) -> None:
    from robomimic_check import assert_robomimic_reads

    env_meta = assert_robomimic_reads(collected[0], OBS_KEYS)
    assert env_meta["type"] == 2


def test_difficulty_groups_cover_metaworlds_50_tasks_once() -> None:
    import metaworld
    from metaworld.policies import ENV_POLICY_MAP

    assert {g: len(t) for g, t in GROUPS.items()} == {"easy": 28, "medium": 11, "hard": 6,
                                                      "very_hard": 5}
    assert len(TASKS) == len(set(TASKS)) == 50
    assert {f"{t}-v3" for t in TASKS} == set(metaworld.ALL_V3_ENVIRONMENTS) == set(ENV_POLICY_MAP)
    assert resolve("all") == list(TASKS) and resolve("Reach-V3") == ["reach"]
    assert resolve("very_hard") == list(GROUPS["very_hard"])


def test_an_unknown_task_or_group_is_one_line_listing_the_valid_names_nearest_first(
        tmp_path: Path) -> None:
    out = tmp_path / "demos.hdf5"
    r = sefa("collect", out, "--env", "metaworld:pick-plce", "--episodes", "1", ok=False)
    assert r.returncode == 1 and not out.exists() and r.stdout == ""
    [line] = r.stderr.strip().splitlines()
    assert line.startswith("error: --env: unknown Meta-World task or group 'pick-plce' (valid, "
                           "nearest first: pick-place, pick-place-wall, ")
    listed = line.split("nearest first: ")[1].rstrip(")").split(", ")
    assert sorted(listed) == sorted([*GROUPS, "all", *TASKS])

    ws = tmp_path / "ws"
    r = sefa("eval", "--env", "metaworld:hardd", "-w", ws, ok=False)
    assert r.returncode == 1 and not ws.exists()
    [line] = r.stderr.strip().splitlines()
    assert "unknown Meta-World task or group 'hardd' (valid, nearest first: hard, " in line

    r = sefa("collect", out, "--env", "metaworld:reach", "--cameras", ok=False)
    assert r.returncode == 1 and not out.exists()
    assert r.stderr.strip().splitlines() == [
        "error: --cameras: --cameras records robosuite Lift's cameras; Meta-World "
        "demonstrations are low-dim"]

    r = sefa("collect", out, "--env", "metaworld:easy", ok=False)
    assert r.returncode == 1 and not out.exists()
    assert r.stderr.strip().splitlines() == [
        "error: --env: collect records one Meta-World task at a time, and 'easy' is a group of 28"]


# a 32x32 MLP flow, 20 training steps per stage, Euler sampling: plumbing, never skill
TINY_PIPELINE = """\
train: ["policy.mlp_hidden_dims=[32,32]", "policy.time_embed_dim=16", "training.max_steps=20",
        "training.batch_size=32", "training.lr_warmup_steps=2", "training.val_every=20",
        "training.checkpoint_every=20", "training.val_batches=1", "training.val_sample_windows=8",
        "flow.solver=euler", "flow.steps=4"]
train_config: {train_config}
reflow: {{iters: 1, samples_per_window: 2, max_windows: 32, solver: euler}}
align: {{eps: 0.05}}
distill: {{align: true, train_overrides: ["training.max_steps=20"]}}
"""


@pytest.mark.parametrize("task", ["reach", "pick-place"])
def test_collect_ingest_tiny_pipeline_and_eval_on_a_task(task: str, tmp_path: Path) -> None:
    """The preset's base config under tiny overrides, through every stage, then rollouts of
    the base flow and the one-step student on test seeds from 100000, kept in the workspace."""
    demos, ws = tmp_path / "demos.hdf5", tmp_path / "ws"
    r = sefa("collect", demos, "--env", f"metaworld:{task}", "--episodes", "3")
    assert "3/3 successful episodes kept" in r.stdout
    sefa("ingest", demos, "-w", ws)  # no --fps: the file records Meta-World's 80 Hz
    (tmp_path / "tiny.yaml").write_text(TINY_PIPELINE.format(
        train_config=REPO / "pipelines" / "metaworld_train.yaml"))
    sefa("run", tmp_path / "tiny.yaml", "-w", ws)
    from sefa_pipelines.overview import _settings, eval_hint

    # `sefa status` suggests the rollouts of the recorded task, a command that runs as it is
    assert eval_hint(ws, _settings(ws)[0]) == f"sefa eval --offline (or --env metaworld:{task})"
    # Meta-World's own name, capitalized: the same evaluation as metaworld:TASK
    rows = json.loads(sefa("eval", "--env", f"metaworld:{task.title()}-v3", "--n-test", "2",
                           "--max-steps", "24", "--json", "-w", ws).stdout)
    assert [r["kind"] for r in rows] == ["base_flow", "reflow_one_step"]
    for row in rows:
        log = json.loads((ws / row["eval_log"]).read_text())
        assert log["env"] == f"metaworld:{task}" and log["tasks"] == [task]
        assert [(p["task"], p["seed"]) for p in log["per_seed"]] == [(task, 100000), (task, 100001)]
        assert all(isinstance(p["success"], bool) and 1 <= p["steps"] <= 24 for p in log["per_seed"])
        assert log["test/success_rate"] == np.mean([p["success"] for p in log["per_seed"]])
        assert log["max_steps"] == 24
    assert all(r["cached_in"].startswith(f"evals/metaworld_{task}-") for r in rows)
    again = json.loads(sefa("eval", "distill", "--env", f"metaworld:{task}", "--n-test", "2",
                            "--max-steps", "24", "--force", "--json", "-w", ws).stdout)
    assert again[0]["cached_in"] == rows[1]["cached_in"]  # the same evaluation, redone
    first = json.loads((ws / rows[1]["eval_log"]).read_text())["per_seed"]
    assert json.loads((ws / again[0]["eval_log"]).read_text())["per_seed"] == first
    if task == "reach":  # once: a whole group, each task on its own goals
        [row] = json.loads(sefa("eval", "distill", "--env", "metaworld:very_hard", "--n-test",
                                "1", "--max-steps", "8", "--json", "-w", ws).stdout)
        log = json.loads((ws / row["eval_log"]).read_text())
        assert list(log["per_task_success_rate"]) == list(GROUPS["very_hard"])
        assert [p["task"] for p in log["per_seed"]] == list(GROUPS["very_hard"])
        assert row["max_steps"] == 8 and row["cached_in"].startswith("evals/metaworld_very_hard-")
    # default episode length: Meta-World's own 500 (the cache key says so)
    from sefa_pipelines.evals import EvalRequest

    assert EvalRequest(f"metaworld:{task}").settings()["max_steps"] == 500
    assert EvalRequest("pusht").settings()["max_steps"] == 300
