"""TF lookups on tf2 messages built from rosbags' own typestore, checked with 4x4 matrices."""

from __future__ import annotations

import numpy as np
from reference_math import matrix
import pytest
from rosbags.typesys import Stores, get_typestore

from sefa_data.errors import SefaInputError
from sefa_data.readers.tf_lookup import (TfCollector, compose, find_chain, invert,
                                         quat_multiply, tf_stream)

T = get_typestore(Stores.ROS2_HUMBLE).types


def random_pose(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    return np.concatenate([rng.normal(size=3), q / np.linalg.norm(q)])


def tf_message(*edges: tuple[str, str, np.ndarray, int]):
    out = []
    for parent, child, p, stamp_ns in edges:
        stamp = T["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9)
        out.append(T["geometry_msgs/msg/TransformStamped"](
            header=T["std_msgs/msg/Header"](stamp=stamp, frame_id=parent), child_frame_id=child,
            transform=T["geometry_msgs/msg/Transform"](
                translation=T["geometry_msgs/msg/Vector3"](x=p[0], y=p[1], z=p[2]),
                rotation=T["geometry_msgs/msg/Quaternion"](x=p[3], y=p[4], z=p[5], w=p[6]))))
    return T["tf2_msgs/msg/TFMessage"](transforms=out)


def test_compose_and_invert_match_matrices():
    rng = np.random.default_rng(0)
    a, b = random_pose(rng), random_pose(rng)
    assert np.allclose(matrix(compose(a, b)), matrix(a) @ matrix(b))
    assert np.allclose(matrix(invert(a)), np.linalg.inv(matrix(a)))
    assert np.allclose(compose(a, invert(a)), [0, 0, 0, 0, 0, 0, 1])
    assert np.allclose(quat_multiply(a[3:], np.array([0, 0, 0, 1.0])), a[3:])


def test_find_chain_walks_up_to_the_common_ancestor():
    parents = {"odom": "map", "base": "odom", "cam": "base", "arm": "base", "other": "world"}
    chain = find_chain(parents, "cam", "arm")
    assert [(s.parent, s.child, s.inverted) for s in chain] == [("base", "cam", True),
                                                                ("base", "arm", False)]
    assert [s.child for s in find_chain(parents, "map", "cam")] == ["odom", "base", "cam"]
    with pytest.raises(SefaInputError, match="different roots"):
        find_chain(parents, "map", "other")
    with pytest.raises(SefaInputError, match="'nope' is not in the TF data"):
        find_chain(parents, "map", "nope")


def test_stream_holds_edges_and_uses_a_late_static_edge_for_all_time():
    rng = np.random.default_rng(1)
    m_o = [random_pose(rng) for _ in range(3)]
    o_b = [random_pose(rng) for _ in range(3)]
    b_cam = random_pose(rng)
    tf = TfCollector()
    tf.add(tf_message(("odom", "base", o_b[0], 100)), log_ns=1000, static=False)  # no map->odom yet
    tf.add(tf_message(("map", "odom", m_o[0], 110)), log_ns=1010, static=False)
    tf.add(tf_message(("/odom", "base", o_b[1], 120), ("map", "odom", m_o[1], 125)), 1020, False)
    tf.add(tf_message(("base", "cam", b_cam, 0)), log_ns=1030, static=True)  # latched, late
    tf.add(tf_message(("odom", "base", o_b[2], 140)), log_ns=1040, static=False)
    tf.add(tf_message(("odom", "wheel", o_b[2], 150)), log_ns=1050, static=False)  # off-chain

    s = tf_stream(tf, ["map", "cam"], key="k", topic="/tf", stamp="header")
    # message 0 dropped (map->odom unknown), one sample per message touching the chain's
    # dynamic edges; the static edge applies before it was recorded
    assert s.times_ns.tolist() == [110, 125, 140]
    assert s.log_times_ns.tolist() == [1010, 1020, 1040]
    held = [(m_o[0], o_b[0]), (m_o[1], o_b[1]), (m_o[1], o_b[2])]
    for value, (a, b) in zip(s.values, held):
        assert np.allclose(matrix(value), matrix(a) @ matrix(b) @ matrix(b_cam))
    assert s.names == ["x", "y", "z", "qx", "qy", "qz", "qw"]

    back = tf_stream(tf, ["cam", "map"], key="k", topic="/tf", stamp="log")
    assert back.times_ns.tolist() == [1010, 1020, 1040]
    assert np.allclose(matrix(back.values[-1]), np.linalg.inv(matrix(s.values[-1])))


def test_static_only_chain_is_one_sample():
    tf = TfCollector()
    p = np.array([1.0, 2, 3, 0, 0, 0, 1])
    tf.add(tf_message(("base", "cam", p, 7)), log_ns=70, static=True)
    s = tf_stream(tf, ["base", "cam"], key="k", topic="/tf_static")
    assert s.times_ns.tolist() == [7] and np.allclose(s.values, [p])


def test_two_parents_is_an_error():
    tf = TfCollector()
    p = np.array([0, 0, 0, 0, 0, 0, 1.0])
    tf.add(tf_message(("a", "c", p, 1), ("b", "c", p, 1)), log_ns=1, static=False)
    with pytest.raises(SefaInputError, match="two parents") as e:
        tf_stream(tf, ["a", "c"], key="pose", topic="/tf")
    assert e.value.key == "pose"
