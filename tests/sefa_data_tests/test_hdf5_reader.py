"""The HDF5 reader against the two real robosuite files and small robomimic-layout files.

No real robomimic file (with obs/ and mask/) is among the shared recordings, so those tests
build small files with h5py in tmp_path, in the layout robomimic documents.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest

from sefa_data.config_io import from_dict
from sefa_data.errors import ConfigError, SefaInputError
from sefa_data.readers.hdf5 import Hdf5Options, options_from_dict, read_hdf5

LIFT = "robosuite141_lift_panda_3demos.hdf5"
HANDOVER = "robosuite141_two_arm_handover_7demos.hdf5"


def _by_suffix(names) -> list[str]:
    return sorted(names, key=lambda n: int(n.split("_")[1]))


# ----------------------------------------------------------------------------- real files

@pytest.mark.parametrize("name, demos", [(LIFT, ["demo_1", "demo_2", "demo_3"]),
                                         (HANDOVER, [f"demo_{i}" for i in range(7)])])
def test_robosuite_file_matches_h5py(shared_data: Path, name: str, demos: list[str]) -> None:
    path = shared_data / name
    rec = read_hdf5(path)
    episodes = list(rec.episodes)
    assert rec.meta["layout"] == "robosuite"
    assert [e.label for e in episodes] == demos == rec.meta["demos"]
    with h5py.File(path, "r") as f:
        assert _by_suffix(f["data"].keys()) == demos
        for ep in episodes:
            group = f["data"][ep.label]
            assert ep.source == str(path)
            assert len(ep) == group["actions"].shape[0]
            assert {len(v) for v in ep.data.values()} == {len(ep)}
            np.testing.assert_array_equal(ep.data["action"], group["actions"][()])
            np.testing.assert_array_equal(ep.data["state"], group["states"][()])
            assert ep.data["action"].dtype == group["actions"].dtype
    assert rec.meta["steps"] == sum(len(e) for e in episodes)


def test_lift_meta(shared_data: Path) -> None:
    meta = read_hdf5(shared_data / LIFT).meta
    assert meta["env"] == "Lift"
    assert meta["env_info"]["controller_configs"]["type"] == "OSC_POSE"  # parsed JSON
    assert meta["total"] is None and meta["warnings"] == []
    assert "fps" not in meta  # the file does not record its control_freq
    assert list(meta["keys"]) == ["action", "state"]


def test_handover_longer_streams_are_skipped(shared_data: Path) -> None:
    rec = read_hdf5(shared_data / HANDOVER)
    episodes = list(rec.episodes)
    skipped = rec.meta["skipped"]
    # the users' input logs run at their own rate: 1380 rows for 641 actions in demo_0
    assert skipped["user_info/0/clutch"] == "1380 rows for 641 actions in demo_0"
    assert "controller_info/teleop_commands/arm1/position" in skipped
    # same length everywhere but float32 in one demo and float64 in the others
    assert "float32" in skipped["controller_info/teleop_controls/arm0/rotation"]
    for ep in episodes:
        assert not any(k.startswith("user_info") for k in ep.data)
        assert {len(v) for v in ep.data.values()} == {len(ep)}
        assert ep.data["interventions"].dtype == bool
    assert rec.meta["env_args"]["env_name"] == "TwoArmHandover"
    assert rec.meta["total"] == 2775 == rec.meta["steps"]
    assert rec.meta["fps"] == 20.0  # env_args.env_kwargs.control_freq
    assert rec.meta["warnings"] == []


# ----------------------------------------------------------------------------- robomimic layout

def _write_robomimic(path: Path, lengths: dict[str, int], *, total: int | None = None,
                     masks: dict[str, list[str]] | None = None) -> Path:
    """A small robomimic-layout file, built here because no real one is in the shared data."""
    rng = np.random.default_rng(0)
    with h5py.File(path, "w") as f:
        data = f.create_group("data")
        data.attrs["env_args"] = json.dumps({"env_name": "Lift", "env_type": 1, "env_kwargs": {}})
        data.attrs["total"] = sum(lengths.values()) if total is None else total
        for demo, n in lengths.items():
            g = data.create_group(demo)
            g["actions"] = rng.uniform(-1, 1, (n, 7))
            g["rewards"] = np.zeros(n)
            g["dones"] = np.arange(n) == n - 1
            g["states"] = rng.normal(size=(n, 10))
            g["obs/robot0_eef_pos"] = rng.normal(size=(n, 3)).astype(np.float32)
            g["obs/agentview_image"] = rng.integers(0, 256, (n, 16, 16, 3), dtype=np.uint8)
            g["next_obs/robot0_eef_pos"] = rng.normal(size=(n, 3)).astype(np.float32)
        for name, demos in (masks or {}).items():
            f[f"mask/{name}"] = np.array([d.encode() for d in demos], dtype="S")
    return path


@pytest.fixture
def robomimic_file(tmp_path: Path) -> Path:
    # demo_10 sorts before demo_2 as a string; demo_1 is missing (a gap)
    return _write_robomimic(tmp_path / "rm.hdf5", {"demo_0": 5, "demo_2": 4, "demo_10": 6},
                            masks={"train": ["demo_0", "demo_10"], "valid": ["demo_2"]})


def test_robomimic_layout(robomimic_file: Path) -> None:
    rec = read_hdf5(robomimic_file)
    episodes = list(rec.episodes)
    assert rec.meta["layout"] == "robomimic"
    assert rec.meta["env_args"]["env_name"] == "Lift"
    assert [e.label for e in episodes] == ["demo_0", "demo_2", "demo_10"]
    assert [len(e) for e in episodes] == [5, 4, 6]
    assert [e.filters for e in episodes] == [{"train"}, {"valid"}, {"train"}]
    assert set(episodes[0].data) == {"action", "observation.robot0_eef_pos",
                                     "observation.agentview_image", "reward", "done"}
    with h5py.File(robomimic_file, "r") as f:
        g = f["data/demo_10"]
        np.testing.assert_array_equal(episodes[2].data["action"], g["actions"][()])
        image = episodes[2].data["observation.agentview_image"]
        assert image.dtype == np.uint8
        np.testing.assert_array_equal(image, g["obs/agentview_image"][()])
    assert rec.meta["filters"] == {"train": ["demo_0", "demo_10"], "valid": ["demo_2"]}


def test_robomimic_options(robomimic_file: Path) -> None:
    options = options_from_dict({"obs_keys": ["robot0_eef_pos"], "filter_key": "train",
                                 "include_rewards": False})
    rec = read_hdf5(robomimic_file, options)
    episodes = list(rec.episodes)
    assert [e.label for e in episodes] == ["demo_0", "demo_10"]
    assert set(episodes[0].data) == {"action", "observation.robot0_eef_pos"}


def test_key_map_layout(robomimic_file: Path) -> None:
    options = Hdf5Options(key_map={"action": "actions", "observation.state": "states",
                                   "next.eef": "next_obs/robot0_eef_pos"})
    rec = read_hdf5(robomimic_file, options)
    ep = next(iter(rec.episodes))
    assert rec.meta["layout"] == "key_map"
    assert set(ep.data) == {"action", "observation.state", "next.eef"}
    assert ep.data["observation.state"].shape == (5, 10)


def test_total_disagreeing_is_a_warning(tmp_path: Path) -> None:
    path = _write_robomimic(tmp_path / "t.hdf5", {"demo_0": 3, "demo_1": 4}, total=10)
    rec = read_hdf5(path)
    assert len(list(rec.episodes)) == 2
    assert rec.meta["warnings"] == ["data.attrs['total'] is 10 but the demos hold 7 steps"]


def test_options_are_strict() -> None:
    with pytest.raises(ConfigError, match="did you mean 'obs_keys'"):
        from_dict(Hdf5Options, {"obs_key": ["x"]})
    with pytest.raises(ConfigError, match="not both"):
        from_dict(Hdf5Options, {"obs_keys": ["x"], "key_map": {"action": "actions"}})


# ----------------------------------------------------------------------------- errors

def _error(path: Path, options: Hdf5Options | None = None) -> SefaInputError:
    """The error of reading `path` to the end, whether it comes from the open or the iterator."""
    with pytest.raises(SefaInputError) as info:
        list(read_hdf5(path, options).episodes)
    assert "\n" not in str(info.value)
    return info.value


def test_missing_file(tmp_path: Path) -> None:
    assert _error(tmp_path / "nope.hdf5").what == "file not found"


def test_not_hdf5(tmp_path: Path) -> None:
    path = tmp_path / "text.hdf5"
    path.write_text("not hdf5\n")
    assert "not a readable HDF5 file" in _error(path).what


def test_truncated_file(shared_data: Path, tmp_path: Path) -> None:
    path = tmp_path / "truncated.hdf5"
    blob = (shared_data / LIFT).read_bytes()
    path.write_bytes(blob[: len(blob) // 2])
    assert "truncated" in _error(path).what


def test_no_data_group(tmp_path: Path) -> None:
    path = tmp_path / "empty.hdf5"
    with h5py.File(path, "w") as f:
        f["other"] = np.zeros(3)
    err = _error(path)
    assert "no 'data' group" in err.what and "other" in err.what


def test_demo_without_actions(tmp_path: Path) -> None:
    path = _write_robomimic(tmp_path / "a.hdf5", {"demo_0": 3, "demo_1": 3})
    with h5py.File(path, "a") as f:
        del f["data/demo_1/actions"]
    rec = read_hdf5(path)
    episodes = rec.episodes
    assert next(episodes).label == "demo_0"  # the good demo comes before the error
    with pytest.raises(SefaInputError) as info:
        next(episodes)
    assert info.value.key == "data/demo_1" and "no action dataset 'actions'" in info.value.what


def test_requested_key_with_wrong_length(tmp_path: Path) -> None:
    path = _write_robomimic(tmp_path / "l.hdf5", {"demo_0": 3, "demo_1": 4})
    with h5py.File(path, "a") as f:
        del f["data/demo_1/obs/robot0_eef_pos"]
        f["data/demo_1/obs/robot0_eef_pos"] = np.zeros((9, 3), np.float32)
    err = _error(path, Hdf5Options(obs_keys=["robot0_eef_pos"]))
    assert err.key == "data/demo_1/obs/robot0_eef_pos" and "9 rows" in err.what
    err = _error(path, Hdf5Options(key_map={"action": "actions",
                                            "eef": "obs/robot0_eef_pos"}))
    assert err.key == "data/demo_1/obs/robot0_eef_pos"
    # not requested but under obs/: still an error naming the demo and the key (it used to be
    # dropped from every demo, silently, with exit status 0)
    err = _error(path)
    assert err.key == "data/demo_1/obs/robot0_eef_pos"
    assert err.what.startswith("9 rows for 4 actions") and "--skip-bad-demos" in err.what
    # asked for: that demo is skipped, the key kept for the others, and a warning says so
    rec = read_hdf5(path, Hdf5Options(skip_bad_demos=True))
    episodes = list(rec.episodes)
    assert [e.label for e in episodes] == ["demo_0"]
    assert "observation.robot0_eef_pos" in episodes[0].data
    assert rec.meta["skipped_demos"] == {
        "demo_1": "data/demo_1/obs/robot0_eef_pos: 9 rows for 4 actions"}
    assert rec.meta["warnings"] == ["skipped demo demo_1 (--skip-bad-demos): "
                                    "data/demo_1/obs/robot0_eef_pos: 9 rows for 4 actions"]


def test_observation_missing_or_of_another_dtype_in_one_demo(tmp_path: Path) -> None:
    path = _write_robomimic(tmp_path / "d.hdf5", {"demo_0": 3, "demo_1": 4, "demo_2": 2})
    with h5py.File(path, "a") as f:
        del f["data/demo_1/obs/robot0_eef_pos"]
        del f["data/demo_2/obs/agentview_image"]
        f["data/demo_2/obs/agentview_image"] = np.zeros((2, 16, 16, 3), np.float32)
    err = _error(path)
    assert (err.key, err.what.split(" (")[0]) == ("data/demo_1/obs/robot0_eef_pos", "missing")
    rec = read_hdf5(path, Hdf5Options(skip_bad_demos=True))
    assert [e.label for e in rec.episodes] == ["demo_0"]
    assert "float32 (16, 16, 3) where demo_0 has uint8 (16, 16, 3)" in \
        rec.meta["skipped_demos"]["demo_2"]


@pytest.mark.parametrize("actions", [np.float64(3.0), np.array([b"left", b"right"])])
def test_scalar_or_string_actions(tmp_path: Path, actions) -> None:
    path = tmp_path / "s.hdf5"
    with h5py.File(path, "w") as f:
        f["data/demo_0/actions"] = actions
        f["data/demo_0/obs/x"] = np.zeros((2, 1))
    err = _error(path)
    assert err.key == "data/demo_0/actions" and "actions must be numbers" in err.what


def test_nan_names_demo_key_and_step(tmp_path: Path) -> None:
    path = _write_robomimic(tmp_path / "n.hdf5", {"demo_0": 3, "demo_1": 6})
    with h5py.File(path, "r+") as f:
        f["data/demo_1/actions"][4, 2] = np.nan
        f["data/demo_1/actions"][5, 0] = np.inf
    err = _error(path)
    assert str(err) == f"{path}: data/demo_1/actions: NaN or Inf value (at step 4)"


def test_empty_demo(tmp_path: Path) -> None:
    path = _write_robomimic(tmp_path / "e.hdf5", {"demo_0": 3, "demo_1": 0})
    err = _error(path)
    assert err.key == "data/demo_1/actions" and "empty demo" in err.what


def test_unknown_filter_key(robomimic_file: Path) -> None:
    err = _error(robomimic_file, Hdf5Options(filter_key="test"))
    assert err.what == "unknown filter key 'test'; available: train, valid"


def test_unknown_filter_key_without_masks(shared_data: Path) -> None:
    err = _error(shared_data / LIFT, Hdf5Options(filter_key="train"))
    assert "the file has no mask group" in err.what


def test_copy_of_real_file_reads_the_same(shared_data: Path, tmp_path: Path) -> None:
    # reading must never depend on the file's name or folder
    copy = tmp_path / "copy.h5"
    shutil.copy(shared_data / LIFT, copy)
    a = [e.data["action"] for e in read_hdf5(shared_data / LIFT).episodes]
    b = [e.data["action"] for e in read_hdf5(copy).episodes]
    assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))


def test_mask_naming_absent_or_no_demos(tmp_path: Path) -> None:
    path = _write_robomimic(tmp_path / "m.hdf5", {"demo_0": 3, "demo_1": 3},
                            masks={"train": ["demo_0", "demo_7"], "none": []})
    err = _error(path, Hdf5Options(filter_key="train"))
    assert (err.key, err.what) == ("mask/train", "lists demos that are not in 'data': demo_7")
    assert _error(path, Hdf5Options(filter_key="none")).what == "lists no demos"


# ----------------------------------------------------------------------------- inspect, scaffold

def test_scaffold_key_map_of_a_custom_layout_ingests_as_it_is(tmp_path: Path) -> None:
    """A layout neither robomimic nor robosuite (written with h5py): the scaffold maps the
    per-step datasets, leaves the event log out with its reason, and ingests unedited."""
    import yaml

    from sefa_data.readers.hdf5 import scaffold_key_map
    from sefa_data.ingest import IngestOptions, ingest
    from sefa_data.store.zarr_store import EpisodeStore

    path = tmp_path / "custom.h5"
    rng = np.random.default_rng(0)
    with h5py.File(path, "w") as f:
        for i, n in enumerate((5, 8)):
            g = f.create_group(f"data/demo_{i}")
            g["commanded_action"] = rng.normal(size=(n, 3))
            g["sensors/joint_pos"] = rng.normal(size=(n, 7)).astype(np.float32)
            g["log/events"] = np.arange(n + 4)
    text = scaffold_key_map(path, fps=15)
    m = yaml.safe_load(text)
    assert m["fps"] == 15
    assert m["key_map"] == {"action": "commanded_action",
                            "sensors.joint_pos": "sensors/joint_pos"}
    assert "#   log/events: 9 rows for 5 actions in demo_0" in text
    (tmp_path / "map.yaml").write_text(text)
    report = ingest([path], tmp_path / "s.zarr", IngestOptions(topic_map=str(tmp_path / "map.yaml")))
    assert report.inputs[0].status == "written"
    store = EpisodeStore.open(tmp_path / "s.zarr")
    assert store.fps == 15 and store.keys == ["action", "sensors.joint_pos"]
    with h5py.File(path, "r") as f:
        np.testing.assert_array_equal(store.get_episode(1)["action"],
                                      f["data/demo_1/commanded_action"][()])


@pytest.mark.parametrize("name", [LIFT, HANDOVER])
def test_scaffold_of_the_real_files_ingests(shared_data: Path, tmp_path: Path, name: str) -> None:
    from sefa_data.readers.hdf5 import scaffold_key_map
    from sefa_data.ingest import IngestOptions, ingest
    from sefa_data.store.zarr_store import EpisodeStore

    text = scaffold_key_map(shared_data / name)
    (tmp_path / "map.yaml").write_text(text)
    # the Lift file records no control_freq: the scaffold says so and the user gives --fps
    fps = 20 if name == LIFT else None
    assert ("# fps: 20  # the file does not record its rate" in text) == (name == LIFT)
    ingest([shared_data / name], tmp_path / "s.zarr",
           IngestOptions(topic_map=str(tmp_path / "map.yaml"), fps=fps))
    direct = read_hdf5(shared_data / name)
    store = EpisodeStore.open(tmp_path / "s.zarr")
    assert sorted(store.keys) == sorted(direct.meta["keys"] | {"action": 1})


def test_inspect_hdf5(shared_data: Path) -> None:
    from sefa_data.readers.hdf5 import inspect_hdf5

    info = inspect_hdf5(shared_data / HANDOVER)
    json.dumps(info)
    assert info["n_demos"] == 7 and info["steps"] == 2775 and info["layout"] == "robosuite"
    assert info["reads"]["state"] == "states" and info["problem"] is None
    assert info["datasets"]["user_info/0/clutch"]["why_not"] == "1380 rows for 641 actions in demo_0"
    assert info["skips"]["user_info/0/clutch"] == "1380 rows for 641 actions in demo_0"
