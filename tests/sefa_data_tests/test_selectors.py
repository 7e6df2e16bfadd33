"""Selectors on rosbags message objects (built from rosbags' own typestore) and on JSON dicts."""

from __future__ import annotations

import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from sefa_data.errors import SefaInputError
from sefa_data.readers.selectors import Selector, parse_selector, select

TS = get_typestore(Stores.ROS2_HUMBLE)
T = TS.types


def header(sec: int = 5, nanosec: int = 7):
    stamp = T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)
    return T["std_msgs/msg/Header"](stamp=stamp, frame_id="odom")


def pose(x: float = 1.0) -> object:
    return T["geometry_msgs/msg/Pose"](
        position=T["geometry_msgs/msg/Point"](x=x, y=2.0, z=3.0),
        orientation=T["geometry_msgs/msg/Quaternion"](x=0.1, y=0.2, z=0.3, w=0.4))


def odometry() -> object:
    vec = T["geometry_msgs/msg/Vector3"]
    twist = T["geometry_msgs/msg/Twist"](linear=vec(x=4.0, y=5.0, z=6.0),
                                         angular=vec(x=7.0, y=8.0, z=9.0))
    return T["nav_msgs/msg/Odometry"](
        header=header(), child_frame_id="base_link",
        pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose(), covariance=np.arange(36.0)),
        twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=np.zeros(36)))


def joint_state(names: list[str], position: list[float]) -> object:
    return T["sensor_msgs/msg/JointState"](header=header(), name=names,
                                           position=np.array(position),
                                           velocity=np.zeros(len(names)), effort=np.array([]))


def test_parse():
    assert parse_selector("").path == ()
    p = parse_selector(" position[ a , b ] ")
    assert p.path == ("position",) and p.pick == ("a", "b") and p.text == "position[a, b]"
    assert parse_selector("pose.pose.position").path == ("pose", "pose", "position")
    for bad in ("position[a,]", "[a]", "pose..x", "pos[a]ition", "position[a"):
        with pytest.raises(SefaInputError):
            parse_selector(bad, key="k")


def test_pose_flattens_in_definition_order():
    values, names = select(odometry(), "pose.pose")
    assert values.tolist() == [1.0, 2.0, 3.0, 0.1, 0.2, 0.3, 0.4]
    assert names == ["position.x", "position.y", "position.z",
                     "orientation.x", "orientation.y", "orientation.z", "orientation.w"]
    values, names = select(odometry(), "twist.twist")
    assert values.tolist() == [4.0, 5.0, 6.0, 7.0, 8.0, 9.0]
    assert names[0] == "linear.x" and names[-1] == "angular.z"
    values, names = select(odometry(), "pose.pose.position.y")
    assert values.tolist() == [2.0] and names == ["y"]


def test_whole_message_skips_header_and_strings():
    values, names = select(odometry(), "")
    # pose 7 + covariance 36 + twist 6 + covariance 36; no header, no child_frame_id
    assert values.shape == (85,)
    assert names[:3] == ["pose.pose.position.x", "pose.pose.position.y", "pose.pose.position.z"]
    assert names[7] == "pose.covariance[0]" and values[7 + 35] == 35.0
    values, names = select(joint_state(["a", "b"], [1.0, 2.0]), "")
    assert values.tolist() == [1.0, 2.0, 0.0, 0.0] and names[0] == "position[0]"


def test_joint_pick_follows_the_selector_order_and_the_name_list():
    sel = Selector("position[c, a]", key="obs")
    assert sel(joint_state(["a", "b", "c"], [1.0, 2.0, 3.0])).tolist() == [3.0, 1.0]
    assert sel.names == ["c", "a"]
    # the publisher reorders its joints: the cached index must follow
    assert sel(joint_state(["c", "b", "a"], [30.0, 20.0, 10.0])).tolist() == [30.0, 10.0]
    assert Selector("velocity[b]")(joint_state(["a", "b"], [1.0, 2.0])).tolist() == [0.0]


def test_joint_pick_errors():
    with pytest.raises(SefaInputError) as e:
        Selector("position[a, z]", key="obs")(joint_state(["a", "b"], [1.0, 2.0]))
    assert e.value.key == "obs" and "'z'" in e.value.what and "available: a, b" in e.value.what
    with pytest.raises(SefaInputError, match="0 values for 2 names"):
        Selector("effort[a]")(joint_state(["a", "b"], [1.0, 2.0]))
    with pytest.raises(SefaInputError, match="no `name` list"):
        Selector("pose.pose.position[x]")(odometry())


def test_unknown_field_lists_the_fields():
    with pytest.raises(SefaInputError) as e:
        Selector("pose.positon", key="obs")(odometry())
    assert e.value.key == "obs"
    assert "field 'pose.positon' not found in nav_msgs/msg/Odometry" in e.value.what
    assert "fields: pose, covariance" in e.value.what
    with pytest.raises(SefaInputError, match="fields: header, child_frame_id, pose, twist"):
        Selector("poze")(odometry())


def test_dicts_from_json():
    msg = {"header": {"stamp": {"sec": 1, "nanosec": 2}, "frame_id": "x"},
           "pos": {"x": 1, "y": 2.5}, "label": "a", "ok": True,
           "arm": {"name": ["j1", "j2"], "position": [0.5, 0.25]}}
    values, names = select(msg, "")
    assert values.tolist() == [1.0, 2.5, 1.0, 0.5, 0.25]
    assert names == ["pos.x", "pos.y", "ok", "arm.position[0]", "arm.position[1]"]
    assert select(msg, "arm.position[j2, j1]")[0].tolist() == [0.25, 0.5]
    sel = Selector("pos", key="k")
    sel(msg)
    with pytest.raises(SefaInputError, match="cannot be read"):
        sel({"pos": {"x": 1}})
