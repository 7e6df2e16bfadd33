"""`sefa ingest` end to end on the real recordings in ../shared/data (issue 2, acceptance 1-4)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
import zarr

from sefa_data.errors import SefaInputError
from sefa_data.ingest import IngestOptions, ingest
from sefa_data.store.zarr_store import EpisodeStore

JOINTS = [f"lwr_arm_{i}_joint" for i in range(7)]
KUKA = ["kuka_lwr_honeypot_joint_states.bag", "kuka_lwr_honeypot_ros2_mcap",
        "kuka_lwr_honeypot_ros2_db3"]


def sefa(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "sefa_cli.main", *map(str, args)], capture_output=True,
                          text=True, cwd=cwd or Path(__file__).resolve().parents[2])


def write_map(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def kuka_map(tmp_path: Path, fps: int) -> Path:
    joints = ", ".join(JOINTS)
    return write_map(tmp_path / f"kuka_{fps}.yaml", f"""
fps: {fps}
features:
  observation.joint_pos: {{topic: /joint_states, field: "position[{joints}]"}}
  observation.joint_vel: {{topic: /joint_states, field: "velocity[{joints}]", resample: linear}}
""")


# ------------------------------------------------------------------------------ Push-T (Zarr)


@pytest.fixture(scope="module")
def pusht_store(shared_data, tmp_path_factory):
    out = tmp_path_factory.mktemp("pusht") / "pusht.zarr"
    report = ingest([shared_data / "pusht_cchi_v7_replay.zarr"], out,
                    IngestOptions(fps=10, renames={"img": "observation.images.top"}))
    assert report.inputs[0].status == "written"
    return out


def test_pusht_ingests_all_206_episodes_and_opens_as_plain_dp_zarr(shared_data, pusht_store):
    src = zarr.open_group(str(shared_data / "pusht_cchi_v7_replay.zarr"), mode="r")
    ours = zarr.open_group(str(pusht_store), mode="r")  # a plain zarr reader, no sefa code
    assert ours.metadata.zarr_format == 2
    ends = ours["meta/episode_ends"][:]
    assert ends.dtype == np.int64 and len(ends) == 206
    np.testing.assert_array_equal(ends, src["meta/episode_ends"][:])
    for key in ("action", "state", "keypoint", "n_contacts"):
        np.testing.assert_array_equal(ours["data"][key][:], src["data"][key][:])
    img = ours["data/observation.images.top"]
    assert img.dtype == np.uint8 and img.chunks == (1, 96, 96, 3) and img.shape == (25650, 96, 96, 3)
    for i in (0, 12345, 25649):
        np.testing.assert_array_equal(img[i], src["data/img"][i].astype(np.uint8))
    attrs = ours.attrs.asdict()
    assert attrs["fps"] == 10
    assert attrs["features"]["observation.images.top"]["type"] == "image"
    assert attrs["sources"][0]["episodes"] == [0, 206]
    assert len(attrs["sources"][0]["sha256"]) == 64
    train, valid = ours["mask/train"][:], ours["mask/valid"][:]
    assert train.sum() + valid.sum() == 206 and valid.sum() == 21
    act = src["data/action"][:].astype(np.float64)
    np.testing.assert_allclose(attrs["stats"]["action"]["mean"], act.mean(0), rtol=1e-6)


def test_pusht_reingest_is_skipped(shared_data, pusht_store):
    before = sorted((p.name, p.stat().st_mtime_ns) for p in pusht_store.rglob(".z*"))
    report = ingest([shared_data / "pusht_cchi_v7_replay.zarr"], pusht_store, IngestOptions(fps=10))
    assert report.inputs[0].status == "skipped"
    assert sorted((p.name, p.stat().st_mtime_ns) for p in pusht_store.rglob(".z*")) == before


def test_inspect_store_json(pusht_store):
    r = sefa("inspect", pusht_store, "--json")
    assert r.returncode == 0, r.stderr
    s = json.loads(r.stdout)
    assert s["n_episodes"] == 206 and s["n_frames"] == 25650
    assert s["features"]["action"]["stats"]["constant"] == [False, False]
    assert s["masks"] == {"train": 185, "valid": 21}
    assert s["episodes"][0]["length"] == 161


# ------------------------------------------------------------------------------ KUKA (ROS 1/2)


@pytest.mark.parametrize("fps", [50, 100])
def test_three_kuka_recordings_give_identical_arrays(shared_data, tmp_path, fps):
    m = kuka_map(tmp_path, fps)
    stores = []
    for name in KUKA:
        out = tmp_path / f"{name}.zarr"
        ingest([shared_data / name], out, IngestOptions(topic_map=str(m)))
        stores.append(EpisodeStore.open(out))
    first = stores[0].get_episode(0)
    # 41 s at 100 Hz in the file; the grid spans the trimmed recording
    assert first["observation.joint_pos"].shape == (int(41.0 * fps) - fps // 50 * 0, 7) or \
        abs(len(first["observation.joint_pos"]) - 41 * fps) <= 1
    for s in stores[1:]:
        ep = s.get_episode(0)
        for key in first:
            np.testing.assert_array_equal(ep[key], first[key])
        np.testing.assert_array_equal(s.root["meta/episode_start_time_ns"][:],
                                      stores[0].root["meta/episode_start_time_ns"][:])
    assert stores[0].attrs["features"]["observation.joint_pos"]["names"] is not None


def test_kuka_at_100hz_reproduces_the_recorded_samples(shared_data, tmp_path):
    """At the recording's own rate, `hold` must return the recorded positions themselves."""
    from rosbags.highlevel import AnyReader

    out = tmp_path / "k.zarr"
    ingest([shared_data / KUKA[0]], out, IngestOptions(topic_map=str(kuka_map(tmp_path, 100))))
    ep = EpisodeStore.open(out).get_episode(0)["observation.joint_pos"]
    with AnyReader([shared_data / KUKA[0]]) as r:
        msgs = [r.deserialize(raw, c.msgtype) for c, _, raw in r.messages()]
    recorded = np.array([m.position for m in msgs], np.float32)
    stamps = np.array([m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in msgs])
    start = EpisodeStore.open(out).root["meta/episode_start_time_ns"][0]
    t = start + np.round(np.arange(len(ep)) * 1e7).astype(np.int64)
    idx = np.searchsorted(stamps, t, side="right") - 1
    np.testing.assert_array_equal(ep, recorded[idx])


# ------------------------------------------------------------------------------ TF and Nav2


def test_tf_bag_ros1_and_ros2_give_identical_base_link_pose(shared_data, tmp_path):
    m = write_map(tmp_path / "tf.yaml", """
fps: 10
stamp: log
features:
  observation.base_pose: {topic: /tf, frames: [odom, base_link]}
""")
    arrays = []
    for name in ("evo_tf_example.bag", "evo_tf_example_ros2"):
        out = tmp_path / f"{name}.zarr"
        ingest([shared_data / name], out, IngestOptions(topic_map=str(m)))
        arrays.append(EpisodeStore.open(out).get_episode(0)["observation.base_pose"])
    assert arrays[0].shape[1] == 7 and len(arrays[0]) > 400
    np.testing.assert_array_equal(arrays[0], arrays[1])
    np.testing.assert_allclose(np.linalg.norm(arrays[0][:, 3:], axis=1), 1.0, atol=1e-5)


NAV2_MAP = """
fps: 10
stamp: {stamp}
{skew}
features:
  observation.pose: {{topic: /odom, field: pose.pose}}
  observation.twist: {{topic: /odom, field: twist.twist}}
"""


def test_nav2_odom_with_header_and_log_stamps_and_the_skew_check(shared_data, tmp_path):
    bag = shared_data / "evo_nav2_turtlebot_sim.mcap"
    # header stamps are simulation time (~928 s), the log time is wall-clock: the check fires
    m = write_map(tmp_path / "h.yaml", NAV2_MAP.format(stamp="header", skew=""))
    with pytest.raises(SefaInputError, match=r"evo_nav2_turtlebot_sim.mcap: observation.pose \(/odom\): header stamps differ from log time by -17782\d+\.\d+ s \(limit 60 s\)"):
        ingest([bag], tmp_path / "x.zarr", IngestOptions(topic_map=str(m)))
    assert not (tmp_path / "x.zarr").exists()
    eps = {}
    for stamp, skew in (("header", "max_stamp_skew_s: null"), ("log", "")):
        m = write_map(tmp_path / f"{stamp}.yaml", NAV2_MAP.format(stamp=stamp, skew=skew))
        out = tmp_path / f"{stamp}.zarr"
        ingest([bag], out, IngestOptions(topic_map=str(m)))
        s = EpisodeStore.open(out)
        eps[stamp] = (s.get_episode(0), int(s.root["meta/episode_start_time_ns"][0]))
    (hdr, t_hdr), (log, t_log) = eps["header"], eps["log"]
    assert 900e9 < t_hdr < 1000e9 and t_log > 1.7e18
    assert hdr["observation.pose"].shape[1] == 7 and hdr["observation.twist"].shape[1] == 6
    assert abs(len(hdr["observation.pose"]) - len(log["observation.pose"])) < 30
    # both clocks describe the same trajectory: same start and end pose within the hold lag
    np.testing.assert_allclose(hdr["observation.pose"][-1, :3], log["observation.pose"][-1, :3], atol=0.05)


def test_skew_check_stays_quiet_on_a_synchronised_real_robot(shared_data, tmp_path):
    m = kuka_map(tmp_path, 50)  # header stamps (stamp: auto) within ms of the log time
    report = ingest([shared_data / KUKA[0]], tmp_path / "k.zarr", IngestOptions(topic_map=str(m)))
    assert report.inputs[0].status == "written"


# ------------------------------------------------------------------------------ robosuite HDF5


@pytest.mark.parametrize("name", ["robosuite141_lift_panda_3demos.hdf5",
                                  "robosuite141_two_arm_handover_7demos.hdf5"])
def test_robosuite_hdf5_matches_h5py(shared_data, tmp_path, name):
    out = tmp_path / "r.zarr"
    ingest([shared_data / name], out, IngestOptions(fps=20))
    store = EpisodeStore.open(out)
    with h5py.File(shared_data / name, "r") as f:
        demos = sorted(f["data"].keys(), key=lambda d: int(d.split("_")[1]))
        assert store.n_episodes == len(demos)
        for i, demo in enumerate(demos):
            ep = store.get_episode(i)
            np.testing.assert_array_equal(ep["action"], f["data"][demo]["actions"][:])
            np.testing.assert_array_equal(ep["state"], f["data"][demo]["states"][:])
    assert store.episode_lengths.tolist() == [len(store.get_episode(i)["action"]) for i in range(len(demos))]
