"""The ROS bag / MCAP reader on the real recordings in ../shared/data and on small built files.

No real recording has camera images, JSON MCAP channels, silent topics, backward header stamps,
marker topics or unknown message types, so those tests write small files with the libraries'
own writers (rosbags `rosbag1.Writer` / `rosbag2.Writer` with a typestore serializer, and
`mcap.writer.Writer`). Truncated and corrupt files are damaged copies of the real ones in
tmp_path; the originals are never touched.
"""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
from reference_math import matrix
import pytest
from mcap.writer import Writer as McapWriter
from PIL import Image
from rosbags.highlevel import AnyReader
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin, Writer as Writer2
from rosbags.typesys import Stores, get_typestore

from sefa_data.config_io import from_dict
from sefa_data.errors import SefaInputError
from sefa_data.readers.ros import inspect_recording, read_streams, scaffold_topic_map
from sefa_data.readers.topic_map import TopicMap, load_topic_map

KUKA = ["kuka_lwr_honeypot_joint_states.bag", "kuka_lwr_honeypot_ros2_mcap",
        "kuka_lwr_honeypot_ros2_db3"]
JOINTS = [f"lwr_arm_{i}_joint" for i in range(7)]
NAV2 = "evo_nav2_turtlebot_sim.mcap"
TS1, TS2 = get_typestore(Stores.ROS1_NOETIC), get_typestore(Stores.ROS2_HUMBLE)


def topic_map(features: dict, **top) -> TopicMap:
    return from_dict(TopicMap, {"fps": 10, "features": features, **top})


def joints(field: str, names: list[str] = JOINTS) -> str:
    return f"{field}[{', '.join(names)}]"


def edge_pose(tf) -> np.ndarray:
    t, r = tf.transform.translation, tf.transform.rotation
    return np.array([t.x, t.y, t.z, r.x, r.y, r.z, r.w])


def raw_messages(path: Path, topic: str) -> list[tuple[int, object]]:
    """(log time, message) straight from rosbags, as the reference for sefa's output."""
    with AnyReader([path]) as r:
        conns = [c for c in r.connections if c.topic == topic]
        return [(t, r.deserialize(raw, c.msgtype)) for c, t, raw in r.messages(connections=conns)]


# --- writers for the files no real recording provides -----------------------------------------


def header(ts, ns: int, frame: str = "base"):
    stamp = ts.types["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)
    if ts is TS1:
        return ts.types["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id=frame)
    return ts.types["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)


def write_ros2(path: Path, types: dict[str, str], messages: list[tuple[str, int, object]],
               storage: StoragePlugin = StoragePlugin.SQLITE3) -> Path:
    with Writer2(path, version=9, storage_plugin=storage) as w:
        conns = {t: w.add_connection(t, typ, typestore=TS2) for t, typ in types.items()}
        for topic, log_ns, msg in messages:
            w.write(conns[topic], log_ns, TS2.serialize_cdr(msg, types[topic]))
    return path


def write_ros1(path: Path, types: dict[str, str], messages: list[tuple[str, int, object]]) -> Path:
    with Writer1(path) as w:
        conns = {t: w.add_connection(t, typ, typestore=TS1) for t, typ in types.items()}
        for topic, log_ns, msg in messages:
            w.write(conns[topic], log_ns, TS1.serialize_ros1(msg, types[topic]))
    return path


def write_mcap(path: Path, channels: dict[str, tuple[str, str, str, bytes]],
               messages: list[tuple[str, int, bytes]], profile: str = "") -> Path:
    """channels: topic -> (message encoding, schema name, schema encoding, schema data)."""
    with open(path, "wb") as f:
        w = McapWriter(f)
        w.start(profile, "sefa-tests")
        ids = {}
        for topic, (encoding, name, schema_encoding, data) in channels.items():
            schema = w.register_schema(name, schema_encoding, data) if name else 0
            ids[topic] = w.register_channel(topic, encoding, schema)
        for topic, log_ns, data in messages:
            w.add_message(ids[topic], log_ns, data, log_ns)
        w.finish()
    return path


def float64(ts, value: float):
    return ts.types["std_msgs/msg/Float64"](data=value)


# --- the real recordings ------------------------------------------------------------------------


@pytest.fixture(scope="module")
def kuka_streams(shared_data: Path) -> dict[str, dict]:
    tmap = topic_map({"state": {"topic": "/joint_states", "field": joints("position")},
                      "vel": {"topic": "/joint_states", "field": joints("velocity")}})
    return {name: read_streams(shared_data / name, tmap)[0] for name in KUKA}


def test_kuka_ros1_ros2_mcap_ros2_db3_are_identical(kuka_streams):
    ref = kuka_streams[KUKA[0]]
    for name in KUKA[1:]:
        for key in ("state", "vel"):
            a, b = ref[key], kuka_streams[name][key]
            assert a.values.shape == (4101, 7) and a.values.dtype == np.float64
            assert np.array_equal(a.values, b.values), (name, key)
            assert np.array_equal(a.times_ns, b.times_ns)
            assert np.array_equal(a.log_times_ns, b.log_times_ns)
            assert b.names == JOINTS and b.topic == "/joint_states"


def test_kuka_values_and_stamps_match_the_messages(kuka_streams, shared_data):
    msgs = raw_messages(shared_data / KUKA[0], "/joint_states")
    s = kuka_streams[KUKA[0]]["state"]
    for i in (0, 2000, 4100):
        log_ns, msg = msgs[i]
        assert np.array_equal(s.values[i], msg.position)  # the bag lists joints 0..6 in order
        assert s.times_ns[i] == msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec  # auto
        assert s.log_times_ns[i] == log_ns
    assert s.times_ns.dtype == np.int64 and s.log_times_ns.dtype == np.int64


def test_joint_pick_order_is_the_selectors(shared_data):
    tmap = topic_map({"s": {"topic": "/joint_states", "field": joints("position", JOINTS[::-1])}})
    s = read_streams(shared_data / KUKA[1], tmap)[0]["s"]
    pos = read_streams(shared_data / KUKA[1], topic_map({"s": {
        "topic": "/joint_states", "field": "position"}}))[0]["s"]
    assert np.array_equal(s.values, pos.values[:, ::-1]) and s.names == JOINTS[::-1]


def test_tf_ros1_and_ros2_give_the_same_base_link_pose(shared_data):
    tmap = topic_map({"base": {"topic": "/tf", "frames": ["odom", "base_link"]}})
    ros1 = read_streams(shared_data / "evo_tf_example.bag", tmap)[0]["base"]
    ros2 = read_streams(shared_data / "evo_tf_example_ros2", tmap)[0]["base"]
    # /tf_static (base_footprint -> base_link) is one latched message recorded first
    assert len(ros1) == 517 and ros1.values.shape == (517, 7)
    for a, b in ((ros1.values, ros2.values), (ros1.times_ns, ros2.times_ns),
                 (ros1.log_times_ns, ros2.log_times_ns)):
        assert np.array_equal(a, b)

    msgs = raw_messages(shared_data / "evo_tf_example.bag", "/tf")
    static = raw_messages(shared_data / "evo_tf_example.bag", "/tf_static")[0][1].transforms[0]
    assert (static.header.frame_id, static.child_frame_id) == ("base_footprint", "base_link")
    for i in (0, 250, 516):
        (edge,) = msgs[i][1].transforms
        assert (edge.header.frame_id, edge.child_frame_id) == ("odom", "base_footprint")
        expected = matrix(edge_pose(edge)) @ matrix(edge_pose(static))
        assert np.allclose(matrix(ros1.values[i]), expected)
        assert ros1.times_ns[i] == edge.header.stamp.sec * 10**9 + edge.header.stamp.nanosec
        assert ros1.log_times_ns[i] == msgs[i][0]


@pytest.fixture(scope="module")
def nav2(shared_data: Path) -> dict:
    tmap = topic_map({
        "pose": {"topic": "/odom", "field": "pose.pose"},
        "twist": {"topic": "/odom", "field": "twist.twist"},
        "pose_log": {"topic": "/odom", "field": "pose.pose", "stamp": "log"},
        "base_in_map": {"topic": "/tf", "frames": ["map", "base_link"]},
        "lidar_in_odom": {"topic": "/tf", "frames": ["odom", "rplidar_link"]},
    }, stamp="header")
    return read_streams(shared_data / NAV2, tmap)[0]


def test_nav2_odometry_header_and_log_stamps(nav2, shared_data):
    pose, twist, log = nav2["pose"], nav2["twist"], nav2["pose_log"]
    assert pose.values.shape == (2639, 7) and twist.values.shape == (2639, 6)
    assert pose.names == ["position.x", "position.y", "position.z", "orientation.x",
                          "orientation.y", "orientation.z", "orientation.w"]
    assert twist.names == ["linear.x", "linear.y", "linear.z",
                           "angular.x", "angular.y", "angular.z"]
    assert 925e9 < pose.times_ns[0] < 935e9  # simulation time
    assert log.times_ns[0] > 1.7e18 and np.array_equal(log.times_ns, pose.log_times_ns)
    msgs = raw_messages(shared_data / NAV2, "/odom")
    log_ns, msg = msgs[1000]
    p = msg.pose.pose
    assert pose.values[1000].tolist() == [p.position.x, p.position.y, p.position.z,
                                          p.orientation.x, p.orientation.y, p.orientation.z,
                                          p.orientation.w]
    assert twist.values[1000, 5] == msg.twist.twist.angular.z
    assert pose.times_ns[1000] == msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
    assert log.times_ns[1000] == log_ns


def test_nav2_tf_chains_through_dynamic_and_static_edges(nav2, shared_data):
    tf = raw_messages(shared_data / NAV2, "/tf")
    static = {t.child_frame_id: edge_pose(t)
              for t in raw_messages(shared_data / NAV2, "/tf_static")[0][1].transforms}
    latest: dict[tuple[str, str], np.ndarray] = {}
    map_odom, odom_base = ("map", "odom"), ("odom", "base_link")
    expected_map, expected_lidar = [], []
    for _, msg in tf:  # replay the edges by hand, holding the latest of each
        touched = set()
        for t in msg.transforms:
            latest[(t.header.frame_id, t.child_frame_id)] = edge_pose(t)
            touched.add((t.header.frame_id, t.child_frame_id))
        if {map_odom, odom_base} & touched and {map_odom, odom_base} <= latest.keys():
            expected_map.append(matrix(latest[map_odom]) @ matrix(latest[odom_base]))
        if odom_base in touched:
            expected_lidar.append(matrix(latest[odom_base]) @ matrix(static["shell_link"])
                                  @ matrix(static["rplidar_link"]))
    base, lidar = nav2["base_in_map"], nav2["lidar_in_odom"]
    assert len(base) == len(expected_map) > 1000 and len(lidar) == len(expected_lidar)
    for i in (0, len(base) // 2, len(base) - 1):
        assert np.allclose(matrix(base.values[i]), expected_map[i])
    for i in (0, len(lidar) - 1):
        assert np.allclose(matrix(lidar.values[i]), expected_lidar[i])


# --- errors -------------------------------------------------------------------------------------


def read_error(path: Path, features: dict, **top) -> SefaInputError:
    with pytest.raises(SefaInputError) as e:
        read_streams(path, topic_map(features, **top))
    assert "\n" not in str(e.value)
    return e.value


def test_missing_topic_lists_the_topics(shared_data):
    e = read_error(shared_data / NAV2, {"x": {"topic": "/odometry"}})
    assert e.key == "x" and e.file == str(shared_data / NAV2)
    assert "/odometry is not in the recording; it has: /amcl_pose, /odom, /tf, /tf_static" in e.what


def test_optional_missing_topic_yields_no_stream(shared_data):
    streams, markers = read_streams(shared_data / KUKA[2], topic_map({
        "state": {"topic": "/joint_states", "field": "position"},
        "gripper": {"topic": "/gripper", "optional": True},
        "cam": {"topic": "/tf", "frames": ["a", "b"], "optional": True}}))
    assert list(streams) == ["state"] and markers.shape == (0,)


def test_unknown_field_and_unknown_joint(shared_data):
    e = read_error(shared_data / NAV2, {"p": {"topic": "/odom", "field": "pose.positon"}})
    assert e.key == "p" and "field 'pose.positon' not found in nav_msgs/msg/Odometry" in e.what
    assert e.where and e.where.startswith("message 0")
    e = read_error(shared_data / KUKA[0], {"s": {"topic": "/joint_states",
                                                 "field": "position[lwr_arm_0_joint, wrist]"}})
    assert e.key == "s" and "'wrist'" in e.what and "lwr_arm_6_joint" in e.what


def test_frames_on_a_non_tf_topic_and_unknown_frame(shared_data):
    e = read_error(shared_data / NAV2, {"p": {"topic": "/odom", "frames": ["odom", "base_link"]}})
    assert "tf2_msgs/msg/TFMessage" in e.what
    e = read_error(shared_data / "evo_tf_example.bag", {"p": {"topic": "/tf",
                                                              "frames": ["odom", "base_lnk"]}})
    assert e.key == "p" and "'base_lnk' is not in the TF data" in e.what


def test_missing_truncated_and_corrupt_files(shared_data, tmp_path):
    features = {"s": {"topic": "/joint_states", "field": "position"}}
    assert "no such file" in read_error(tmp_path / "gone.bag", features).what
    for name in (KUKA[0], NAV2):
        data = (shared_data / name).read_bytes()
        cut = tmp_path / f"cut_{name}"
        cut.write_bytes(data[:len(data) // 2])
        assert "truncated or corrupt" in read_error(cut, features).what
        garbage = tmp_path / f"garbage_{name}"
        garbage.write_bytes(b"not a recording " * 64)
        assert "truncated or corrupt" in read_error(garbage, features).what
    # damage in the middle of the data: found during the pass, with where it happened
    data = bytearray((shared_data / KUKA[0]).read_bytes())
    middle = len(data) // 2
    data[middle:middle + 4096] = b"\xff" * 4096
    damaged = tmp_path / "damaged.bag"
    damaged.write_bytes(bytes(data))
    e = read_error(damaged, features)
    assert "truncated or corrupt" in e.what and e.where and e.where.startswith("message ")


def test_silent_topic(tmp_path):
    bag = write_ros2(tmp_path / "silent", {"/a": "std_msgs/msg/Float64",
                                           "/quiet": "std_msgs/msg/Float64"},
                     [("/a", 10, float64(TS2, 1.0))])
    e = read_error(bag, {"a": {"topic": "/a"}, "q": {"topic": "/quiet"}})
    assert e.key == "q" and "has no messages (silent)" in e.what
    streams, _ = read_streams(bag, topic_map({"a": {"topic": "/a"},
                                              "q": {"topic": "/quiet", "optional": True}}))
    assert list(streams) == ["a"] and streams["a"].values.tolist() == [[1.0]]


def test_unknown_message_types(tmp_path):
    msgdef, _ = TS2.generate_msgdef("std_msgs/msg/Float64", ros_version=2)
    cdr = TS2.serialize_cdr(float64(TS2, 2.0), "std_msgs/msg/Float64")
    ros = write_mcap(tmp_path / "schemaless.mcap", {
        "/a": ("cdr", "std_msgs/msg/Float64", "ros2msg", msgdef.encode()),
        "/b": ("cdr", "", "", b"")}, [("/a", 1, cdr), ("/b", 2, cdr)], profile="ros2")
    assert read_streams(ros, topic_map({"a": {"topic": "/a"}}))[0]["a"].values.tolist() == [[2.0]]
    e = read_error(ros, {"b": {"topic": "/b"}})
    assert e.key == "/b" and "unknown message type" in e.what
    proto = write_mcap(tmp_path / "proto.mcap", {
        "/p": ("protobuf", "foo.Bar", "protobuf", b"\x00"),
        "/j": ("json", "", "", b"")}, [("/p", 1, b"\x08\x01"), ("/j", 2, b'{"v": 1}')])
    e = read_error(proto, {"p": {"topic": "/p"}})
    assert e.key == "/p" and "unknown message type 'foo.Bar' (protobuf" in e.what


def test_shape_change_names_the_message(tmp_path):
    def js(n: int):
        return TS2.types["sensor_msgs/msg/JointState"](
            header=header(TS2, 5), name=[f"j{i}" for i in range(n)], position=np.zeros(n),
            velocity=np.zeros(n), effort=np.zeros(n))
    bag = write_ros2(tmp_path / "grow", {"/js": "sensor_msgs/msg/JointState"},
                     [("/js", 10, js(2)), ("/js", 20, js(2)), ("/js", 30, js(3))])
    e = read_error(bag, {"p": {"topic": "/js", "field": "position"}})
    assert e.key == "p" and "from (2,) to (3,)" in e.what and e.where.startswith("message 2")


def test_header_stamp_requested_on_a_headerless_message(tmp_path):
    bag = write_ros2(tmp_path / "plain", {"/a": "std_msgs/msg/Float64"},
                     [("/a", 1, float64(TS2, 1.0))])
    e = read_error(bag, {"a": {"topic": "/a", "stamp": "header"}})
    assert e.key == "a" and "has no header" in e.what
    s = read_streams(bag, topic_map({"a": {"topic": "/a"}}))[0]["a"]  # auto: the log time
    assert s.times_ns.tolist() == [1] == s.log_times_ns.tolist()


# --- order and markers --------------------------------------------------------------------------


def test_samples_stay_in_recorded_order_and_markers_are_log_times(tmp_path):
    """Header stamps that go backwards are kept as recorded: time_align reports them."""
    t = TS1.types

    def pose_at(ns: int, x: float):
        pose = t["geometry_msgs/msg/Pose"](
            position=t["geometry_msgs/msg/Point"](x=x, y=0.0, z=0.0),
            orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0))
        return t["geometry_msgs/msg/PoseStamped"](header=header(TS1, ns), pose=pose)
    empty = t["std_msgs/msg/Empty"]()
    bag = write_ros1(tmp_path / "order.bag", {"/pose": "geometry_msgs/msg/PoseStamped",
                                              "/episode_start": "std_msgs/msg/Empty"}, [
        ("/episode_start", 5, empty), ("/pose", 10, pose_at(300, 1.0)),
        ("/pose", 20, pose_at(100, 2.0)), ("/episode_start", 25, empty),
        ("/pose", 30, pose_at(200, 3.0))])
    tmap = topic_map({"p": {"topic": "/pose", "field": "pose.position.x"}},
                     split={"marker_topic": "/episode_start"})
    streams, markers = read_streams(bag, tmap)
    p = streams["p"]
    assert p.times_ns.tolist() == [300, 100, 200] and p.log_times_ns.tolist() == [10, 20, 30]
    assert p.values[:, 0].tolist() == [1.0, 2.0, 3.0] and p.names == ["x"]
    assert markers.tolist() == [5, 25] and markers.dtype == np.int64


# --- JSON MCAP ----------------------------------------------------------------------------------


def test_json_mcap_and_a_mixed_mcap_in_one_pass(tmp_path):
    schema = json.dumps({"type": "object"}).encode()
    msgdef, _ = TS2.generate_msgdef("std_msgs/msg/Float64", ros_version=2)
    messages, expected = [], []
    for i in range(5):
        body = {"header": {"stamp": {"sec": 100 + i, "nanosec": 5}, "frame_id": "w"},
                "label": "grip", "gripper": {"width": 0.01 * i},
                "arm": {"name": ["b", "a"], "position": [float(i), -float(i)]}}
        messages.append(("/state", 1000 + i, json.dumps(body).encode()))
        messages.append(("/ros", 1000 + i, TS2.serialize_cdr(float64(TS2, 10.0 * i),
                                                             "std_msgs/msg/Float64")))
        expected.append([0.01 * i, -float(i), float(i)])
    path = write_mcap(tmp_path / "mixed.mcap", {
        "/state": ("json", "robot.State", "jsonschema", schema),
        "/ros": ("cdr", "std_msgs/msg/Float64", "ros2msg", msgdef.encode())}, messages)
    streams, _ = read_streams(path, topic_map({
        "grip": {"topic": "/state", "field": "gripper.width"},
        "arm": {"topic": "/state", "field": "arm.position[a, b]"},
        "all": {"topic": "/state"},
        "ros": {"topic": "/ros", "field": "data"}}))
    assert np.allclose(np.hstack([streams["grip"].values, streams["arm"].values]), expected)
    assert streams["arm"].times_ns.tolist() == [(100 + i) * 10**9 + 5 for i in range(5)]
    assert streams["arm"].log_times_ns.tolist() == [1000 + i for i in range(5)]
    assert streams["all"].names == ["gripper.width", "arm.position[0]", "arm.position[1]"]
    assert streams["ros"].values[:, 0].tolist() == [0.0, 10.0, 20.0, 30.0, 40.0]
    assert streams["ros"].times_ns.tolist() == [1000 + i for i in range(5)]  # no header: log
    info = inspect_recording(path)
    assert info["topics"]["/state"]["count"] == 5 and info["format"] == "mcap (cdr, json)"
    assert info["topics"]["/state"]["type"] == "robot.State"


# --- images -------------------------------------------------------------------------------------


def image_messages(ts, rgb: np.ndarray, t0: int) -> tuple[dict[str, str], list]:
    """One topic per raw encoding plus PNG and JPEG CompressedImage, each showing `rgb`."""
    h, w, _ = rgb.shape
    alpha = np.full((h, w, 1), 255, np.uint8)
    raw = {"rgb8": rgb, "bgr8": rgb[..., ::-1], "rgba8": np.concatenate([rgb, alpha], 2),
           "bgra8": np.concatenate([rgb[..., ::-1], alpha], 2), "mono8": rgb[..., :1]}
    types, msgs = {}, []
    for enc, pixels in raw.items():
        step = w * pixels.shape[2] + 2  # two bytes of row padding
        rows = np.zeros((h, step), np.uint8)
        rows[:, :w * pixels.shape[2]] = pixels.reshape(h, -1)
        types[f"/{enc}"] = "sensor_msgs/msg/Image"
        msgs.append((f"/{enc}", t0, ts.types["sensor_msgs/msg/Image"](
            header=header(ts, t0), height=h, width=w, encoding=enc, is_bigendian=0, step=step,
            data=rows.reshape(-1))))
    for fmt in ("png", "jpeg"):
        buf = io.BytesIO()
        Image.fromarray(rgb).save(buf, format=fmt.upper())
        types[f"/{fmt}"] = "sensor_msgs/msg/CompressedImage"
        msgs.append((f"/{fmt}", t0, ts.types["sensor_msgs/msg/CompressedImage"](
            header=header(ts, t0), format=fmt, data=np.frombuffer(buf.getvalue(), np.uint8))))
    return types, msgs


def test_images_raw_and_compressed_ros2_and_ros1(tmp_path):
    y, x = np.mgrid[0:8, 0:12]
    rgb = np.stack([y * 30, x * 20, (x + y) * 10], axis=-1).astype(np.uint8)  # smooth for JPEG
    types, msgs = image_messages(TS2, rgb, 1000)
    _, later = image_messages(TS2, rgb[::-1].copy(), 2000)
    bag = write_ros2(tmp_path / "cams", types, msgs + later, storage=StoragePlugin.MCAP)
    features = {t.strip("/"): {"topic": t, "image_size": [8, 12]} for t in types}
    features["small"] = {"topic": "/png", "image_size": [4, 6]}
    streams, _ = read_streams(bag, topic_map(features))
    for enc in ("rgb8", "bgr8", "rgba8", "bgra8", "png"):
        s = streams[enc]
        assert s.values.dtype == np.uint8 and s.values.shape == (2, 8, 12, 3), enc
        assert np.array_equal(s.values[0], rgb) and np.array_equal(s.values[1], rgb[::-1]), enc
        assert s.names is None and s.times_ns.tolist() == [1000, 2000]
    assert np.array_equal(streams["mono8"].values[0], np.repeat(rgb[..., :1], 3, axis=2))
    assert np.abs(streams["jpeg"].values[0].astype(int) - rgb).mean() < 4
    small = np.asarray(Image.fromarray(rgb).resize((6, 4), Image.Resampling.BILINEAR))
    assert streams["small"].values.shape == (2, 4, 6, 3)
    assert np.array_equal(streams["small"].values[0], small)

    types1, msgs1 = image_messages(TS1, rgb, 1000)
    bag1 = write_ros1(tmp_path / "cams.bag", types1, msgs1)
    s1 = read_streams(bag1, topic_map({"c": {"topic": "/bgr8", "image_size": [8, 12]}}))[0]["c"]
    assert np.array_equal(s1.values[0], rgb)


def test_unsupported_image_encoding(tmp_path):
    img = TS2.types["sensor_msgs/msg/Image"](header=header(TS2, 1), height=2, width=2,
                                              encoding="16UC1", is_bigendian=0, step=4,
                                              data=np.zeros(8, np.uint8))
    bag = write_ros2(tmp_path / "depth", {"/depth": "sensor_msgs/msg/Image"}, [("/depth", 1, img)])
    e = read_error(bag, {"d": {"topic": "/depth", "image_size": [2, 2]}})
    assert e.key == "d" and "'16UC1' is not supported" in e.what


# Decoding in worker processes. No real recording has camera images, so the first Push-T
# episodes are written as recordings with rosbags' own writers (sefa_data.bench.pusht_bags).


@pytest.fixture(scope="module")
def pusht_bags(shared_data, tmp_path_factory) -> dict:
    """The first three Push-T episodes (420 frames) as a ROS 1 bag of JPEG CompressedImages
    and an MCAP bag of raw rgb8 Images, beside the agent state and action."""
    from sefa_data.bench import pusht_bags as pb

    frames = pb.pusht_frames(shared_data, 300)
    d = tmp_path_factory.mktemp("pusht_bags")
    return {(c, m): pb.write_recording(d / pb.recording_name(c, m), frames, c, m)
            for c, m in (("ros1", "compressed"), ("mcap", "raw"))}


@pytest.fixture
def workers_from_the_start(monkeypatch):
    """Decode pools even for a few images, with their workers up before the first message
    (in a real ingest the reader decodes while they start, and a small file would be read
    before they are up)."""
    from sefa_data.readers import image_decode, ros as ros_reader

    monkeypatch.setattr(ros_reader, "MIN_IMAGES_FOR_POOL", 0)
    init = image_decode.DecodePool.__init__

    def started(self, workers):
        init(self, workers)
        if self._starter is not None:
            self._starter.join()
    monkeypatch.setattr(image_decode.DecodePool, "__init__", started)


def store_bytes(root: Path) -> dict[str, bytes]:
    return {p.relative_to(root).as_posix(): p.read_bytes()
            for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("kind, size", [(("ros1", "compressed"), 84), (("mcap", "raw"), 96)])
def test_decode_workers_write_the_same_store_bytes(pusht_bags, tmp_path, monkeypatch,
                                                  workers_from_the_start, kind, size):
    """Images decoded in worker processes, and by the reader whenever the workers are behind,
    make the same store, byte for byte, as the reader decoding alone."""
    from sefa_data.readers import image_decode
    from sefa_data.ingest import IngestOptions, ingest
    from sefa_data.bench.pusht_bags import topic_map_text

    handed_to_workers = []
    submit = image_decode.DecodePool.submit

    def counting_submit(self, *args):
        handle = submit(self, *args)
        handed_to_workers.append(not isinstance(handle, image_decode._Done))
        return handle
    monkeypatch.setattr(image_decode.DecodePool, "submit", counting_submit)
    tmap = tmp_path / "map.yaml"
    tmap.write_text(topic_map_text(kind[1], (size, size)))
    stores = {}
    for workers in (0, 2):
        handed_to_workers.clear()
        stores[workers] = tmp_path / f"w{workers}.zarr"
        ingest([pusht_bags[kind]], stores[workers],
               IngestOptions(topic_map=str(tmap), decode_workers=workers))
        assert any(handed_to_workers) == (workers > 0)
    serial, parallel = store_bytes(stores[0]), store_bytes(stores[2])
    assert sorted(serial) == sorted(parallel) and len(serial) > 420
    assert [k for k in serial if serial[k] != parallel[k]] == []


@pytest.mark.parametrize("workers", [0, 2])
def test_corrupt_compressed_image_is_one_line_naming_file_key_and_message(
        tmp_path, workers_from_the_start, workers):
    """A bag written with rosbags' writer whose JPEG number 100 is cut short, and whose
    message 150 of another topic is garbage: the image comes first in the file, so it is the
    error, in one line with the file, the feature and the message, wherever images decode."""
    y, x = np.mgrid[0:16, 0:16]
    rgb = np.stack([y * 15, x * 15, (x + y) * 7], axis=-1).astype(np.uint8)
    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, format="JPEG", quality=90)
    jpeg = np.frombuffer(buf.getvalue(), np.uint8)
    types = {"/cam": "sensor_msgs/msg/CompressedImage", "/x": "std_msgs/msg/Float64"}
    bag = tmp_path / "cams"
    with Writer2(bag, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conns = {t: w.add_connection(t, typ, typestore=TS2) for t, typ in types.items()}
        for i in range(200):
            ns = 10**9 + i * 10**8
            data = jpeg[:len(jpeg) // 2] if i == 100 else jpeg
            img = TS2.types[types["/cam"]](header=header(TS2, ns), format="jpeg", data=data)
            w.write(conns["/cam"], ns, TS2.serialize_cdr(img, types["/cam"]))
            x_cdr = TS2.serialize_cdr(float64(TS2, i), types["/x"])
            w.write(conns["/x"], ns, x_cdr[:3] if i == 150 else x_cdr)
    with pytest.raises(SefaInputError) as e:
        read_streams(bag, topic_map({"cam": {"topic": "/cam", "image_size": [16, 16]},
                                     "x": {"topic": "/x", "field": "data"}}), workers)
    line = e.value.line()
    assert "\n" not in line and e.value.file == str(bag) and e.value.key == "cam"
    assert e.value.what.startswith("cannot decode the compressed image (jpeg): ")
    assert e.value.where == "message 100, log time 11.000000 s"


# --- inspect and scaffold -----------------------------------------------------------------------


def test_inspect_kuka_and_nav2(shared_data):
    info = inspect_recording(shared_data / KUKA[0])
    json.dumps(info)
    js = info["topics"]["/joint_states"]
    assert info["format"] == "ros1 bag" and js["count"] == 4101 == info["message_count"]
    assert js["type"] == "sensor_msgs/msg/JointState"
    assert 99 < js["rate_hz"] < 101 and 0.009 < js["max_gap_s"] < 0.05
    assert abs(js["skew_median_s"]) < 1
    assert js["last_time_s"] - js["first_time_s"] == pytest.approx(41, abs=0.1)
    nav = inspect_recording(shared_data / NAV2)["topics"]
    assert nav["/odom"]["count"] == 2639 and 26 < nav["/odom"]["rate_hz"] < 28
    assert nav["/odom"]["skew_median_s"] < -1e9  # sim-time header stamps against wall-clock log
    assert nav["/tf_static"]["count"] == 1 and nav["/tf_static"]["rate_hz"] is None


@pytest.mark.parametrize("name", KUKA + ["evo_tf_example.bag", "evo_tf_example_ros2", NAV2])
def test_scaffold_loads_back_and_reads(shared_data, tmp_path, name):
    text = scaffold_topic_map(shared_data / name)
    (tmp_path / "map.yaml").write_text(text)
    tmap = load_topic_map(tmp_path / "map.yaml")
    streams, _ = read_streams(shared_data / name, tmap)
    assert set(streams) == set(tmap.features)
    if name in KUKA:
        (spec,) = tmap.features.values()
        assert spec.field == joints("position") and tmap.fps == 100
    if name == NAV2:
        assert tmap.stamp == "log"  # header stamps are sim time
        assert tmap.features["observation.odom"].field == "pose.pose"
        assert tmap.features["observation.base_link_pose"].frames == ["odom", "base_link"]
    assert load_topic_map(tmp_path / "map.yaml", {"fps": 7}).fps == 7
    assert "fps: 7" in scaffold_topic_map(shared_data / name, fps=7)
