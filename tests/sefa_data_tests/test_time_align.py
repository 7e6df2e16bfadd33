"""Resampling, trimming, segmentation and stream checks on constructed streams with known answers."""

import numpy as np
import pytest

from sefa_data.config_io import from_dict
from sefa_data.episode import Stream
from sefa_data.errors import SefaInputError
from sefa_data.readers.time_align import align_streams, grid, resample, segment_bounds
from sefa_data.readers.topic_map import TopicMap

S = 1_000_000_000


def tmap(**features):
    fps = features.pop("fps", 10)
    extra = features.pop("extra", {})
    return from_dict(TopicMap, {"fps": fps, "features": features, **extra})


def stream(key, t_s, values, log_offset_s=0.0):
    t = np.round(np.asarray(t_s) * S).astype(np.int64)
    return Stream(key=key, topic=f"/{key}", times_ns=t, values=np.asarray(values, np.float64),
                  log_times_ns=t + int(log_offset_s * S))


def test_grid_has_no_rounding_drift():
    t = grid(0, 10 * S, 30.0)
    assert len(t) == 301
    assert t[-1] == 10 * S
    assert t[1] == 33_333_333


def test_hold_takes_latest_sample_at_or_before():
    times = np.array([0, 100, 200, 300]) * 1_000_000
    values = np.array([[0.0], [1.0], [2.0], [3.0]])
    t = np.array([0, 50, 100, 199, 250, 300]) * 1_000_000
    np.testing.assert_array_equal(resample(times, values, t, "hold", 0)[:, 0], [0, 0, 1, 1, 2, 3])


def test_nearest_picks_closest_and_enforces_tolerance():
    times = np.array([0, 100, 200]) * 1_000_000
    values = np.array([[0.0], [1.0], [2.0]])
    t = np.array([0, 40, 60, 140, 200]) * 1_000_000
    out = resample(times, values, t, "nearest", 50e6)
    np.testing.assert_array_equal(out[:, 0], [0, 0, 1, 1, 2])
    with pytest.raises(ValueError, match="no sample within"):
        resample(times, values, np.array([0, 400]) * 1_000_000, "nearest", 50e6)


def test_linear_interpolates_each_dimension():
    times = np.array([0, 1, 2]) * S
    values = np.array([[0.0, 10.0], [1.0, 20.0], [3.0, 20.0]])
    out = resample(times, values, np.array([0, S // 2, S, 3 * S // 2]), "linear", 0)
    np.testing.assert_allclose(out, [[0, 10], [0.5, 15], [1, 20], [2, 20]])


def test_episode_is_trimmed_to_span_where_all_required_keys_have_data():
    m = tmap(a={"topic": "/a"}, b={"topic": "/b"}, fps=10)
    streams = {"a": stream("a", np.arange(0, 3.01, 0.01), np.arange(301)[:, None]),
               "b": stream("b", [0.5, 1.0, 2.05], [[5.0], [6.0], [7.0]])}
    (ep,) = align_streams(streams, m, "rec.bag")
    assert ep.start_time_ns == S // 2
    assert len(ep) == 16  # 0.5 s .. 2.0 s at 10 Hz (2.05 s is the last b sample)
    np.testing.assert_array_equal(ep.data["b"][:, 0], [5] * 5 + [6] * 11)
    np.testing.assert_array_equal(ep.data["a"][:, 0], np.arange(50, 201, 10))
    assert ep.data["a"].dtype == np.float32


def test_optional_key_starting_late_is_back_filled_and_never_trims():
    m = tmap(a={"topic": "/a"}, o={"topic": "/o", "optional": True}, fps=1)
    streams = {"a": stream("a", [0, 1, 2, 3], [[0.0], [1.0], [2.0], [3.0]]),
               "o": stream("o", [2.5], [[9.0]])}
    (ep,) = align_streams(streams, m, "rec.bag")
    assert len(ep) == 4
    np.testing.assert_array_equal(ep.data["o"][:, 0], [9, 9, 9, 9])


def test_split_on_time_gap_and_on_marker():
    times = np.concatenate([np.arange(0, 2, 0.1), np.arange(10, 12, 0.1)]) * S
    assert segment_bounds(times.astype(np.int64), 1.0, None) == [
        (0, 10 * S), (10 * S, int(times[-1]) + 1)]
    m = tmap(a={"topic": "/a"}, fps=10, extra={"split": {"gap_s": 1.0}})
    eps = align_streams({"a": stream("a", times / S, np.arange(40)[:, None])}, m, "rec.bag")
    assert [len(e) for e in eps] == [20, 20]
    assert eps[1].data["a"][0, 0] == 20
    m = tmap(a={"topic": "/a"}, fps=10)
    t = np.arange(0, 4, 0.1)
    eps = align_streams({"a": stream("a", t, np.arange(40)[:, None])}, m, "rec.bag",
                        markers_ns=np.array([2 * S]))
    assert [len(e) for e in eps] == [20, 20]


@pytest.mark.parametrize("case,message", [
    ("backwards", "timestamps go backwards by 0.050000 s"),
    ("nan", "NaN or Inf value"),
    ("empty", "no samples: the topic is silent"),
    ("skew", "header stamps differ from log time by -100.000 s (limit 60 s)"),
])
def test_bad_streams_give_one_line_naming_file_key_and_time(case, message):
    m = tmap(a={"topic": "/a"}, fps=10)
    t = np.arange(0, 1, 0.1)
    v = np.zeros((10, 1))
    offset = 0.0
    if case == "backwards":
        t[5] = t[4] - 0.05
    if case == "nan":
        v[7] = np.nan
    if case == "empty":
        t, v = t[:0], v[:0]
    if case == "skew":
        offset = 100.0
    with pytest.raises(SefaInputError) as e:
        align_streams({"a": stream("a", t, v, offset)}, m, "rec.bag")
    line = str(e.value)
    assert line.startswith("rec.bag: a (/a): ") and message in line
    assert "\n" not in line
    if case in ("backwards", "nan"):
        assert f"message {5 if case == 'backwards' else 7}, t=" in line


def test_clock_skew_is_not_checked_for_log_stamps_or_when_disabled():
    t = np.arange(0, 1, 0.1)
    for extra in ({"stamp": "log"}, {"max_stamp_skew_s": None}):
        m = tmap(a={"topic": "/a"}, fps=10, extra=extra)
        (ep,) = align_streams({"a": stream("a", t, np.zeros((10, 1)), 100.0)}, m, "rec.bag")
        assert len(ep) == 10
