"""Bad input through `sefa ingest`: one error line naming file, key and place; exit 1; store untouched.

Each case appends to an existing store (built from a real KUKA bag) and checks the message, the
exit status and that every byte of the store is unchanged. The commands run in-process through
sefa_cli.main.main; Ctrl-C during an ingest runs in a real child. Recordings with defects that no real
file has (backwards stamps, NaN, a shape change, a silent topic) are written in the test with
rosbags' own writer.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from cli_inprocess import run_cli

REPO = Path(__file__).resolve().parents[2]
JOINTS = [f"lwr_arm_{i}_joint" for i in range(7)]


def sefa(*args) -> subprocess.CompletedProcess:
    """`sefa ARGS` in-process through sefa_cli.main.main (tests/cli_inprocess.py); Ctrl-C runs in a
    real child process (interrupt_ingest), as do tests/sefa_data_tests/test_bad_input_catalogue.py's cases."""
    return run_cli(*args, cwd=REPO)


def snapshot(path: Path) -> dict[str, bytes]:
    return {str(p.relative_to(path)): p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file()}


def write_joint_bag(path: Path, stamps_s, positions, names=("j0", "j1"), silent_topic=False) -> Path:
    """A ROS 2 bag (MCAP storage) of sensor_msgs/JointState, written with rosbags' writer."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    with Writer(path, version=8, storage_plugin=StoragePlugin.MCAP) as w:
        conn = w.add_connection("/joint_states", "sensor_msgs/msg/JointState", typestore=ts)
        if silent_topic:
            w.add_connection("/gripper", "sensor_msgs/msg/JointState", typestore=ts)
        log_ns = 1_000 * 10**9
        for stamp, pos in zip(stamps_s, positions):
            ns = int(round((1_000 + stamp) * 1e9))
            header = T["std_msgs/msg/Header"](
                stamp=T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9), frame_id="")
            pos = np.asarray(pos, np.float64)
            msg = T["sensor_msgs/msg/JointState"](header=header, name=list(names)[:len(pos)],
                                                  position=pos, velocity=np.zeros(0), effort=np.zeros(0))
            w.write(conn, log_ns, ts.serialize_cdr(msg, conn.msgtype))
            log_ns += 10_000_000
    return path


MAP = """
fps: 10
features:
  observation.state: {topic: /joint_states, field: position}
"""


@pytest.fixture
def synth_store(tmp_path):
    """A store built from a good synthetic bag, plus its map: the target of every bad append."""
    (tmp_path / "map.yaml").write_text(MAP)
    good = write_joint_bag(tmp_path / "good", np.arange(0, 2, 0.01), np.ones((200, 2)))
    store = tmp_path / "s.zarr"
    r = sefa("ingest", good, "--map", tmp_path / "map.yaml", "--out", store)
    assert r.returncode == 0, r.stderr
    return store, tmp_path / "map.yaml"


def check_rejected(r, store, before, *fragments):
    assert r.returncode == 1, (r.stdout, r.stderr)
    line = r.stderr.strip().splitlines()[-1]
    assert line.startswith("error: ")
    for f in fragments:
        assert f in line, line
    assert "Traceback" not in r.stderr
    assert snapshot(store) == before


def test_backwards_timestamps(synth_store, tmp_path):
    store, m = synth_store
    stamps = np.arange(0, 2, 0.01)
    stamps[50] = stamps[49] - 0.02
    bag = write_joint_bag(tmp_path / "back", stamps, np.ones((200, 2)))
    before = snapshot(store)
    check_rejected(sefa("ingest", bag, "--map", m, "--out", store), store, before,
                   str(bag), "observation.state (/joint_states)", "timestamps go backwards",
                   "message 50, t=1000.470000 s")


def test_nan_value(synth_store, tmp_path):
    store, m = synth_store
    pos = np.ones((200, 2))
    pos[77, 1] = np.nan
    bag = write_joint_bag(tmp_path / "nan", np.arange(0, 2, 0.01), pos)
    before = snapshot(store)
    check_rejected(sefa("ingest", bag, "--map", m, "--out", store), store, before,
                   str(bag), "observation.state", "NaN or Inf", "message 77")


def test_shape_change_inside_a_key(synth_store, tmp_path):
    store, m = synth_store
    pos = [np.ones(2)] * 100 + [np.ones(3)] * 100
    bag = write_joint_bag(tmp_path / "shape", np.arange(0, 2, 0.01), pos, names=("a", "b", "c"))
    before = snapshot(store)
    check_rejected(sefa("ingest", bag, "--map", m, "--out", store), store, before,
                   str(bag), "observation.state", "(2,)", "(3,)", "100")


def test_required_topic_missing_and_silent(synth_store, tmp_path):
    store, _ = synth_store
    bag = write_joint_bag(tmp_path / "silent", np.arange(0, 2, 0.01), np.ones((200, 2)),
                          silent_topic=True)
    before = snapshot(store)
    m = tmp_path / "m2.yaml"
    m.write_text(MAP + "  observation.gripper: {topic: /gripper, field: position}\n")
    check_rejected(sefa("ingest", bag, "--map", m, "--out", store), store, before,
                   str(bag), "/gripper", "silent")
    m.write_text(MAP + "  observation.gripper: {topic: /nope, field: position}\n")
    check_rejected(sefa("ingest", bag, "--map", m, "--out", store), store, before,
                   str(bag), "/nope", "/joint_states")


def test_empty_recording(synth_store, tmp_path):
    store, m = synth_store
    bag = write_joint_bag(tmp_path / "empty", [], [])
    before = snapshot(store)
    check_rejected(sefa("ingest", bag, "--map", m, "--out", store), store, before,
                   str(bag), "/joint_states")


def test_unknown_map_key(synth_store, tmp_path):
    store, _ = synth_store
    m = tmp_path / "typo.yaml"
    m.write_text(MAP.replace("field:", "feild:"))
    before = snapshot(store)
    check_rejected(sefa("ingest", tmp_path / "good", "--map", m, "--out", store), store, before,
                   str(m), "features.observation.state", "unknown key 'feild'", "did you mean 'field'?")


def test_missing_truncated_and_corrupt_files(shared_data, synth_store, tmp_path):
    store, m = synth_store
    before = snapshot(store)
    check_rejected(sefa("ingest", tmp_path / "nope.bag", "--map", m, "--out", store), store, before,
                   "nope.bag", "no such file")
    real = (shared_data / "kuka_lwr_honeypot_joint_states.bag").read_bytes()
    truncated = tmp_path / "truncated.bag"
    truncated.write_bytes(real[: len(real) // 2])
    check_rejected(sefa("ingest", truncated, "--map", m, "--out", store), store, before,
                   str(truncated))
    corrupt = tmp_path / "corrupt.mcap"
    corrupt.write_bytes(b"\x89MCAP0\r\n" + bytes(range(256)) * 40)
    check_rejected(sefa("ingest", corrupt, "--map", m, "--out", store), store, before, str(corrupt))
    h5 = tmp_path / "truncated.hdf5"
    h5.write_bytes((shared_data / "robosuite141_lift_panda_3demos.hdf5").read_bytes()[:100_000])
    check_rejected(sefa("ingest", h5, "--out", store, "--fps", 10), store, before, str(h5))


def test_header_clock_skew(shared_data, synth_store, tmp_path):
    store, _ = synth_store
    m = tmp_path / "odom.yaml"
    m.write_text("fps: 10\nfeatures:\n  observation.state: {topic: /odom, field: pose.pose.position}\n")
    before = snapshot(store)
    check_rejected(sefa("ingest", shared_data / "evo_nav2_turtlebot_sim.mcap", "--map", m,
                        "--out", store), store, before,
                   "evo_nav2_turtlebot_sim.mcap", "/odom", "header stamps differ from log time",
                   "limit 60 s", "message 0")


def test_hdf5_nan_and_wrong_schema(synth_store, tmp_path):
    """Small robomimic-layout files made with h5py: no real file has these defects."""
    store, _ = synth_store
    before = snapshot(store)
    bad = tmp_path / "nan.hdf5"
    with h5py.File(bad, "w") as f:
        g = f.create_group("data/demo_0")
        a = np.zeros((10, 2))
        a[4, 0] = np.inf
        g["actions"] = a
        g["obs/state"] = np.zeros((10, 2))
    check_rejected(sefa("ingest", bad, "--out", store, "--fps", 10), store, before,
                   str(bad), "demo_0", "action", "4")
    schema = tmp_path / "schema.hdf5"
    with h5py.File(schema, "w") as f:
        f["something/else"] = np.zeros(3)
    check_rejected(sefa("ingest", schema, "--out", store, "--fps", 10), store, before,
                   str(schema), "data")


def test_wrong_keys_for_the_store(shared_data, synth_store):
    store, _ = synth_store
    before = snapshot(store)
    check_rejected(sefa("ingest", shared_data / "robosuite141_lift_panda_3demos.hdf5", "--out", store,
                        "--fps", 10), store, before, "robosuite141_lift_panda_3demos.hdf5",
                   "key not in the store")


def test_skip_failed_goes_on_and_lists_failures(synth_store, tmp_path):
    store, m = synth_store
    stamps = np.arange(0, 2, 0.01)
    stamps[10] = 0
    bad = write_joint_bag(tmp_path / "bad", stamps, np.ones((200, 2)))
    good = write_joint_bag(tmp_path / "good2", np.arange(0, 3, 0.01), np.zeros((300, 2)))
    r = sefa("ingest", bad, good, "--map", m, "--out", store, "--skip-failed")
    assert r.returncode == 1
    assert "1 input(s) failed:" in r.stderr and "timestamps go backwards" in r.stderr
    from sefa_data.store.zarr_store import EpisodeStore

    s = EpisodeStore.open(store)
    assert s.n_episodes == 2 and [src["path"] for src in s.attrs["sources"]][-1] == str(good)


def test_dry_run_writes_nothing(synth_store, tmp_path):
    store, m = synth_store
    good = write_joint_bag(tmp_path / "good3", np.arange(0, 3, 0.01), np.zeros((300, 2)))
    before = snapshot(store)
    r = sefa("ingest", good, "--map", m, "--out", store, "--dry-run")
    assert r.returncode == 0, r.stderr
    assert "would write" in r.stderr and "1 episodes, 30 frames" in r.stderr
    assert snapshot(store) == before
    r = sefa("ingest", good, "--map", m, "--out", tmp_path / "new.zarr", "--dry-run")
    assert r.returncode == 0 and not (tmp_path / "new.zarr").exists()


def small_pusht_like(path: Path, shared_data: Path) -> Path:
    """The first two Push-T episodes as a new DP store (written with zarr): a different file
    with the same keys, so that the real Push-T store can be appended to it."""
    import zarr

    src = zarr.open_group(str(shared_data / "pusht_cchi_v7_replay.zarr"), mode="r")
    ends = src["meta/episode_ends"][:2]
    root = zarr.open_group(str(path), mode="w", zarr_format=2)
    for key in src["data"].array_keys():
        root.create_array(f"data/{key}", data=src["data"][key][: ends[-1]])
    root.create_array("meta/episode_ends", data=ends)
    return path


def interrupt_ingest(args, started, delay: float = 0.0) -> str:
    import signal
    import time

    # a shell runs background jobs with SIGINT ignored, and Python keeps it ignored: restore the
    # default so that the test means the same under `make test &` as in a terminal
    proc = subprocess.Popen([sys.executable, "-m", "sefa_cli.main", "ingest", *map(str, args)],
                            cwd=REPO, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.time() + 60
    while time.time() < deadline and not started():
        time.sleep(0.001)
    assert started(), "the append never started"
    # soon: on a fast disk the whole write phase takes well under a second
    time.sleep(delay)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert "interrupted" in err.splitlines()[-1]
    return err


def test_ctrl_c_during_ingest_leaves_store_intact(shared_data, tmp_path):
    """A real SIGINT to a running `sefa ingest` of Push-T, into an existing and into a new store."""
    store = tmp_path / "p.zarr"
    small = small_pusht_like(tmp_path / "small.zarr", shared_data)
    assert sefa("ingest", small, "--out", store, "--fps", 10).returncode == 0
    before = snapshot(store)
    interrupt_ingest([shared_data / "pusht_cchi_v7_replay.zarr", "--out", store, "--fps", 10],
                     lambda: (store / ".sefa-journal").exists())
    assert snapshot(store) == before
    assert not [p.name for p in store.iterdir() if p.name.startswith(".sefa-journal")]
    new = tmp_path / "new.zarr"
    interrupt_ingest([shared_data / "pusht_cchi_v7_replay.zarr", "--out", new, "--fps", 10],
                     lambda: any(p.name.startswith(".new.zarr.tmp") for p in tmp_path.iterdir()),
                     delay=0.1)  # past the new store's first metadata writes (zarr's own I/O thread)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.zarr", "small.zarr"]
