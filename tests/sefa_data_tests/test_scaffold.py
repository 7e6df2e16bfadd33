"""ROS names as ROS allows them, and scaffolded maps that ingest as they are (issue 12, build 5).

The real recordings in ../shared/data (KUKA in three formats, the evo TF bags, the nav2 MCAP)
each get a scaffold that `sefa ingest` must take without edits. The awkward cases no real file
has (relative topic names, /rosout as the fastest topic, a NaN topic, a topic with one message,
a topic that never changes, a message type with constants) are in one bag written here with
rosbags' own rosbag2 writer.
"""

from __future__ import annotations

import subprocess
from pathlib import Path

import numpy as np
import pytest
import yaml
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from cli_inprocess import run_cli
from sefa_data.readers.ros import scaffold_topic_map
from sefa_data.store.zarr_store import EpisodeStore

REPO = Path(__file__).resolve().parents[2]
REAL = ["kuka_lwr_honeypot_joint_states.bag", "kuka_lwr_honeypot_ros2_mcap",
        "kuka_lwr_honeypot_ros2_db3", "evo_tf_example.bag", "evo_tf_example_ros2",
        "evo_nav2_turtlebot_sim.mcap"]
TS = get_typestore(Stores.ROS2_HUMBLE)
T = TS.types


def sefa(*args) -> subprocess.CompletedProcess:
    """`sefa ARGS` in-process through sefa_cli.main.main (tests/cli_inprocess.py)."""
    return run_cli(*args, cwd=REPO)


@pytest.mark.parametrize("name", REAL)
def test_scaffold_of_every_real_recording_ingests_without_edits(shared_data, tmp_path, name):
    m = tmp_path / "map.yaml"
    r = sefa("ingest", "--scaffold", shared_data / name, "--map", m)
    assert r.returncode == 0, r.stderr
    r = sefa("ingest", shared_data / name, "--map", m, "--out", tmp_path / "s.zarr")
    assert r.returncode == 0, r.stderr
    store = EpisodeStore.open(tmp_path / "s.zarr")
    assert store.n_frames > 400
    assert set(store.keys) == set(yaml.safe_load(m.read_text())["features"])


def header(ns: int):
    return T["std_msgs/msg/Header"](
        stamp=T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9), frame_id="")


def awkward_bag(path: Path) -> Path:
    """Relative topic names, a log topic faster than everything else, NaN values, one message,
    a constant topic, and NavSatFix (whose type declares constants)."""
    types = {"joint_states": "sensor_msgs/msg/JointState",  # relative: no leading '/'
             "/rosout": "rcl_interfaces/msg/Log",
             "/temperature": "sensor_msgs/msg/Temperature",  # has a NaN
             "/once": "std_msgs/msg/Float64",  # one message
             "/flat": "std_msgs/msg/Float64",  # never changes
             "gps/fix": "sensor_msgs/msg/NavSatFix"}
    t0 = 1_700_000_000 * 10**9
    with Writer(path, version=8, storage_plugin=StoragePlugin.MCAP) as w:
        conns = {t: w.add_connection(t, typ, typestore=TS) for t, typ in types.items()}

        def put(topic, ns, msg):
            w.write(conns[topic], ns, TS.serialize_cdr(msg, types[topic]))

        for i in range(200):  # 2 s at 100 Hz
            ns = t0 + i * 10_000_000
            put("joint_states", ns, T["sensor_msgs/msg/JointState"](
                header=header(ns), name=["a", "b"], position=np.array([i * 0.01, -i * 0.01]),
                velocity=np.zeros(0), effort=np.zeros(0)))
            for k in range(3):  # /rosout at 300 Hz: it must not set the fps
                put("/rosout", ns + k, T["rcl_interfaces/msg/Log"](
                    stamp=T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9),
                    level=20, name="n", msg="hello", file="f", function="g", line=i))
            if i % 10 == 0:
                put("/temperature", ns, T["sensor_msgs/msg/Temperature"](
                    header=header(ns), temperature=np.nan if i == 100 else 20.0 + i,
                    variance=0.1 * i))
                put("/flat", ns, T["std_msgs/msg/Float64"](data=1.5))
                put("gps/fix", ns, T["sensor_msgs/msg/NavSatFix"](
                    header=header(ns), status=T["sensor_msgs/msg/NavSatStatus"](status=0,
                                                                                 service=1),
                    latitude=48.0 + i * 1e-5, longitude=11.0, altitude=500.0,
                    position_covariance=np.arange(9.0) + i, position_covariance_type=2))
        put("/once", t0 + 10**9, T["std_msgs/msg/Float64"](data=3.0))
    return path


def test_awkward_bag_scaffold_explains_each_left_out_topic_and_ingests(tmp_path):
    bag = awkward_bag(tmp_path / "awkward")
    text = scaffold_topic_map(bag)
    features = yaml.safe_load(text)["features"]
    by_topic = {f["topic"]: k for k, f in features.items()}
    assert set(by_topic) == {"joint_states", "gps/fix"}  # relative names, as recorded
    assert yaml.safe_load(text)["fps"] == 100  # from joint_states, not /rosout's 300 Hz
    left_out = text[text.index("# Not mapped:"):]
    assert "/rosout (rcl_interfaces/msg/Log): log and diagnostics messages" in left_out
    assert "/temperature (sensor_msgs/msg/Temperature): NaN or Inf value" in left_out
    assert "/once (std_msgs/msg/Float64): too few messages (1)" in left_out
    assert "/flat (std_msgs/msg/Float64): only constants" in left_out
    m = tmp_path / "map.yaml"
    m.write_text(text)
    r = sefa("ingest", bag, "--map", m, "--out", tmp_path / "s.zarr")
    assert r.returncode == 0, r.stderr
    store = EpisodeStore.open(tmp_path / "s.zarr")
    ep = store.get_episode(0)
    # NavSatFix without its declared constants (STATUS_FIX, COVARIANCE_TYPE_KNOWN, ...):
    # status, service, latitude, longitude, altitude, 9 covariances, covariance type
    gps = ep[by_topic["gps/fix"]]
    assert gps.shape[1] == 15
    names = store.attrs["features"][by_topic["gps/fix"]]["names"]
    assert not any(n.isupper() or "STATUS_" in n or "COVARIANCE_TYPE_" in n for n in names)
    np.testing.assert_allclose(ep[by_topic["joint_states"]][:5, 0], [0, 0.01, 0.02, 0.03, 0.04],
                               atol=1e-6)


def test_relative_and_absolute_spellings_both_find_the_topic(tmp_path):
    bag = awkward_bag(tmp_path / "awkward")
    for spelling in ("joint_states", "/joint_states"):
        m = tmp_path / "m.yaml"
        m.write_text(f"fps: 10\nfeatures:\n  observation.state: {{topic: {spelling}, "
                     "field: position}\n")
        out = tmp_path / f"{spelling.strip('/')}{len(spelling)}.zarr"
        r = sefa("ingest", bag, "--map", m, "--out", out)
        assert r.returncode == 0, r.stderr
        assert EpisodeStore.open(out).get_episode(0)["observation.state"].shape == (20, 2)


def test_a_scaffold_that_maps_nothing_still_writes_the_map_to_select_a_field_in(tmp_path):
    """A bag (written with rosbags) whose one topic is a PoseArray: a list of messages, which
    no feature can take whole. The scaffold writes the map anyway, the topic's reason and a
    commented feature to fill in inside, and says so; the map as written (no feature yet) is
    refused by ingest with one error line, writing nothing."""
    path = tmp_path / "poses"
    t0 = 1_700_000_000 * 10**9
    with Writer(path, version=8, storage_plugin=StoragePlugin.MCAP) as w:
        conn = w.add_connection("/poses", "geometry_msgs/msg/PoseArray", typestore=TS)
        for i in range(50):
            ns = t0 + i * 100_000_000
            pose = T["geometry_msgs/msg/Pose"](
                position=T["geometry_msgs/msg/Point"](x=0.01 * i, y=0.0, z=1.0),
                orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0))
            w.write(conn, ns, TS.serialize_cdr(T["geometry_msgs/msg/PoseArray"](
                header=header(ns), poses=[pose]), "geometry_msgs/msg/PoseArray"))
    m = tmp_path / "map.yaml"
    r = sefa("ingest", "--scaffold", path, "--map", m)
    assert r.returncode == 0, r.stderr
    text = m.read_text()
    assert "#   /poses (geometry_msgs/msg/PoseArray): field 'poses' is a list of messages" in text
    assert "  # action:\n  #   topic: /TOPIC\n  #   field: FIELD" in text
    assert yaml.safe_load(text)["features"] is None  # nothing mapped until the user selects
    assert r.stderr.strip().splitlines()[-1].startswith(
        "warning: no topic of poses ingests as a feature as it is (1 listed in the map with the "
        "reason): the map names no feature yet; in it, select a numeric field"), r.stderr
    r = sefa("ingest", path, "--map", m, "--out", tmp_path / "s.zarr")
    last = r.stderr.strip().splitlines()[-1]
    assert r.returncode == 1 and last == f"error: {m}: features: expected a mapping, got None"
    assert "Traceback" not in r.stderr and not (tmp_path / "s.zarr").exists()


def test_an_hdf5_scaffold_on_stdout_ingests_as_it_is(shared_data, tmp_path):
    """Without --map the starter map goes to stdout, nothing else there; the real robosuite Lift
    file's key map (with --fps, which the file does not record) ingests without edits."""
    r = sefa("ingest", "--scaffold", shared_data / "robosuite141_lift_panda_3demos.hdf5",
             "--fps", "20")
    assert r.returncode == 0 and r.stderr == "", r.stderr
    m = tmp_path / "map.yaml"
    m.write_text(r.stdout)
    assert yaml.safe_load(r.stdout)["key_map"] == {"action": "actions", "state": "states"}
    r = sefa("ingest", shared_data / "robosuite141_lift_panda_3demos.hdf5", "--map", m,
             "--out", tmp_path / "s.zarr")
    assert r.returncode == 0, r.stderr
    store = EpisodeStore.open(tmp_path / "s.zarr")
    assert len(store.episode_ends) == 3 and set(store.keys) == {"action", "state"}


@pytest.mark.parametrize("name,what", [("pusht_cchi_v7_replay.zarr", "Zarr store"),
                                       ("lerobot_pusht_v30", "LeRobot dataset")])
def test_a_store_or_a_lerobot_dataset_needs_no_scaffold(shared_data, tmp_path, name, what):
    """One line naming the input, exit 1, no map written."""
    m = tmp_path / "map.yaml"
    r = sefa("ingest", "--scaffold", shared_data / name, "--map", m)
    assert r.returncode == 1 and r.stdout == ""
    assert r.stderr == (f"error: {shared_data / name}: a {what} needs no map (choose keys with "
                        "--key and --rename)\n")
    assert not m.exists()


def test_a_scaffold_reads_one_recording(shared_data, tmp_path):
    bag = shared_data / "kuka_lwr_honeypot_joint_states.bag"
    r = sefa("ingest", "--scaffold", bag, bag, "--map", tmp_path / "map.yaml")
    assert (r.returncode, r.stderr) == (1, "error: --scaffold reads one recording, got 2\n")
    assert not (tmp_path / "map.yaml").exists()
