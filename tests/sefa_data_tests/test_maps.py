"""Topic maps that cannot mean what they say are refused; what they can mean is read as written
(issue 12, build 6). The CLI runs of these cases are in the bad-input catalogue; these are the
in-process checks of the messages and of the one explicit way out (allow_lossy_cast). The bag is
written with rosbags' own writer (tests/bad_inputs.py)."""

from __future__ import annotations

import numpy as np
import pytest

from bad_inputs import MAP, write_bag
from sefa_data.config_io import from_dict
from sefa_data.errors import ConfigError, SefaInputError
from sefa_data.ingest import IngestOptions, ingest
from sefa_data.readers.topic_map import TopicMap, load_topic_map
from sefa_data.validate import lossy_cast
from sefa_data.store.zarr_store import EpisodeStore


def tmap(**top) -> dict:
    return {"fps": 10, "features": {"s": {"topic": "/joint_states", "field": "position"}}, **top}


@pytest.mark.parametrize("change, key, what", [
    ({"fps": float("nan")}, "fps", "positive, finite frame rate"),
    ({"fps": 1e7}, "fps", "up to 10000 Hz"),
    ({"min_length": 0}, "min_length", "at least 1 frame"),
    ({"split": {"gap_s": -2.0}}, "split.gap_s", "positive number of seconds"),
    ({"split": {"gap_s": 0}}, "split.gap_s", "positive number of seconds"),
    ({"max_stamp_skew_s": -1}, "max_stamp_skew_s", ">= 0"),
    ({"tolerance_s": float("inf")}, "tolerance_s", "positive number of seconds"),
])
def test_values_that_cannot_mean_anything(change, key, what):
    with pytest.raises(ConfigError) as e:
        from_dict(TopicMap, tmap(**change), source="m.yaml")
    assert e.value.key == key and what in e.value.what


@pytest.mark.parametrize("feature, what", [
    ({"topic": "/joint_states", "dtype": "float128x"}, "unknown or non-numeric dtype"),
    ({"topic": "/joint_states", "dtype": "str"}, "unknown or non-numeric dtype"),
    ({"topic": "", "field": "position"}, "is empty"),
    ({"topic": "/a b"}, "spaces"),
    ({"topic": "/cam", "image_size": [0, 96]}, "sizes from 1 to 16384"),
])
def test_features_that_cannot_mean_anything(feature, what):
    with pytest.raises(ConfigError, match=what):
        from_dict(TopicMap, {"fps": 10, "features": {"k": feature}})


@pytest.mark.parametrize("key", ["", " a", "a/b", "..", "a..b", ".hidden", "a\\b", "x\ny"])
def test_dataset_keys_that_are_not_array_names(key):
    with pytest.raises(ConfigError, match="keys become array names"):
        from_dict(TopicMap, {"fps": 10, "features": {key: {"topic": "/x"}}})


def test_duplicate_keys_anywhere_in_a_yaml_config(tmp_path):
    m = tmp_path / "m.yaml"
    m.write_text("fps: 10\nfps: 20\nfeatures: {s: {topic: /x}}\n")
    with pytest.raises(ConfigError, match=r"key 'fps' appears twice in one mapping \(first at "
                                          r"line 1\) \(at line 2\)"):
        load_topic_map(m)


def test_lossy_cast_values():
    assert lossy_cast(np.array([1.0, 2.0]), np.dtype(np.uint8)) is None  # whole and in range
    assert "0.5 becomes 0" in lossy_cast(np.array([0.5]), np.dtype(np.uint8))
    assert "300 becomes 44" in lossy_cast(np.array([300]), np.dtype(np.uint8))
    assert lossy_cast(np.array([0.1], np.float64), np.dtype(np.float32)) is None  # precision only
    assert "1e+300 becomes inf" in lossy_cast(np.array([1e300]), np.dtype(np.float32))


def test_lossy_cast_only_when_asked(tmp_path):
    bag = write_bag(tmp_path / "bag")
    m = tmp_path / "m.yaml"
    m.write_text(MAP.replace("field: position}", "field: position, dtype: int8}"))
    with pytest.raises(SefaInputError, match=r"observation.state \(/joint_states\): dtype int8 "
                                             r"cannot hold these values: float64 value 0.3 "
                                             r"becomes 0 as int8 \(38 of 40 values change\); "
                                             r"set allow_lossy_cast: true"):
        ingest([bag], tmp_path / "a.zarr", IngestOptions(topic_map=str(m)))
    assert not (tmp_path / "a.zarr").exists()
    m.write_text(MAP.replace("field: position}",
                             "field: position, dtype: int8, allow_lossy_cast: true}"))
    ingest([bag], tmp_path / "b.zarr", IngestOptions(topic_map=str(m)))
    state = EpisodeStore.open(tmp_path / "b.zarr").get_episode(0)["observation.state"]
    # the recorded positions, 0.3 + 0.01 i and -0.2, at every 10th message, truncated
    expected = np.stack([0.3 + np.arange(0, 200, 10) * 0.01, np.full(20, -0.2)], 1)
    assert state.dtype == np.int8
    np.testing.assert_array_equal(state, expected.astype(np.float32).astype(np.int8))
