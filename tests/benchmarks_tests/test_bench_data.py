"""`sefa bench data`: the throughput library on small real inputs, and its CLI.

Quick by construction: the ingest measurement runs on the KUKA ROS1 bag only (4,101 messages;
Push-T's 25,650 image files would take tens of seconds), the image ingest benchmark on the
first Push-T episode (161 frames), and the sampler runs for a fraction of a second per case on
small Push-T stores built in tmp_path.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from sefa_cli.bench import bench_app
from sefa_data.errors import SefaInputError
from sefa_data.ingest import IngestOptions, ingest
from sefa_data.bench.throughput import (
    RECORDING_NAMES,
    image_ingest_throughput,
    ingest_throughput,
    machine_description,
    sampler_throughput,
)

PUSHT = "pusht_cchi_v7_replay.zarr"
REPO = Path(__file__).resolve().parents[2]


def test_ingest_throughput_measures_the_requested_recording_only(shared_data, tmp_path):
    r = ingest_throughput(shared_data, repeat=1, only=["kuka_ros1"], disk_dir=tmp_path)
    assert [row["name"] for row in r["rows"]] == ["kuka_ros1"]
    row = r["rows"][0]
    assert row["messages"] == 4101
    assert row["raw_s"] > 0 and row["raw_msgs_per_s"] == pytest.approx(4101 / row["raw_s"])
    for where in ("ram", "disk"):
        assert row[f"ours_{where}_s"] > 0
        assert row[f"ours_{where}_msgs_per_s"] == pytest.approx(4101 / row[f"ours_{where}_s"])
        # the ratio is our rate over the raw reader's rate
        assert row[f"ratio_{where}"] == pytest.approx(
            row[f"ours_{where}_msgs_per_s"] / row["raw_msgs_per_s"])
        assert r["lowest_ratio"][where] == row[f"ratio_{where}"]
    assert r["repeat"] == 1 and r["disk_dir"] == str(tmp_path)
    assert list(tmp_path.iterdir()) == []  # the scratch stores are gone


def test_missing_data_dir_is_one_line_naming_the_path(tmp_path):
    missing = tmp_path / "no_such_data"
    for call in (lambda: ingest_throughput(missing, repeat=1),
                 lambda: sampler_throughput(None, data_dir=missing)):
        with pytest.raises(SefaInputError) as e:
            call()
        assert str(missing) in e.value.line() and "\n" not in e.value.line()


def test_unknown_recording_name_lists_the_known_ones(tmp_path):
    with pytest.raises(SefaInputError, match="kuka_ros1, kuka_mcap, pusht"):
        ingest_throughput(tmp_path, only=["kuka_ros3"])
    assert RECORDING_NAMES == ("kuka_ros1", "kuka_mcap", "pusht")


def test_sampler_throughput_on_a_low_dim_store(shared_data, tmp_path):
    store = tmp_path / "lowdim.zarr"
    ingest([shared_data / PUSHT], store, IngestOptions(fps=10, keys=["keypoint", "state", "action"]))
    r = sampler_throughput(store, batch=32, seconds=0.1)
    assert [row["case"] for row in r["rows"]] == ["low_dim_batch", "low_dim_window"]
    rates = {row["case"]: row["windows_per_s"] for row in r["rows"]}
    assert all(v > 0 for v in rates.values())
    assert r["batch_over_window"]["low_dim"] == pytest.approx(
        rates["low_dim_batch"] / rates["low_dim_window"])
    assert r["batch_over_window"]["images"] is None and r["image_cache"] is None
    assert r["windows"] > 1000 and r["batch"] == 32 and r["store"] == str(store)
    assert (r["horizon"], r["n_obs_steps"], r["n_action_steps"]) == (16, 2, 8)


@pytest.fixture(scope="module")
def small_pusht(shared_data, tmp_path_factory):
    """A data folder holding the first ten real Push-T episodes under Push-T's file name
    (written with zarr, as test_training does), so that the image paths run without a
    25,650-frame ingest."""
    import zarr

    src = zarr.open_group(str(shared_data / PUSHT), mode="r")
    ends = src["meta/episode_ends"][:10]
    data = tmp_path_factory.mktemp("small_data")
    root = zarr.open_group(str(data / PUSHT), mode="w", zarr_format=2)
    for key in ("img", "keypoint", "state", "action"):
        root.create_array(f"data/{key}", data=src["data"][key][: ends[-1]])
    root.create_array("meta/episode_ends", data=ends)
    return data


def test_sampler_throughput_with_images(small_pusht, tmp_path):
    store = tmp_path / "s.zarr"
    ingest([small_pusht / PUSHT], store, IngestOptions(fps=10))
    r = sampler_throughput(store, batch=16, seconds=0.1)
    rates = {row["case"]: row["windows_per_s"] for row in r["rows"]}
    assert list(rates) == ["low_dim_batch", "low_dim_window", "images_batch",
                           "images_batch_to_torch", "images_window", "images_zarr_batch"]
    assert all(v > 0 for v in rates.values())
    assert r["batch_over_window"]["images"] == pytest.approx(
        rates["images_batch"] / rates["images_window"])
    cache = r["image_cache"]
    assert cache["frames"] > 0 and 0 <= cache["hit_rate"] <= 1


def test_machine_description():
    m = machine_description()
    assert m["cpu"] and m["cores"] >= 1 and m["python"].count(".") == 2
    assert m["torch"] and m["torch_threads"] >= 1


def test_image_ingest_benchmark_json_and_pixels(shared_data, tmp_path):
    """benchmarks/bench_image_ingest.py on the first Push-T episode: every recording and size
    is a row, the ratio is ingest over decoding, and the stores hold the source frames (raw
    images exactly, JPEG within its error); the recordings are kept in --work."""
    r = subprocess.run([sys.executable, str(REPO / "benchmarks" / "bench_image_ingest.py"),
                        "--data", str(shared_data), "--frames", "100", "--repeat", "1",
                        "--work", str(tmp_path), "--json"],
                       cwd=REPO, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    result = json.loads(r.stdout)
    assert result["frames"] == 161 and result["episodes"] == 1  # Push-T's first episode
    assert result["decode_workers"] == 0  # too few frames to start a decode pool
    rows = {(row["container"], row["message"], tuple(row["image_size"])): row
            for row in result["rows"]}
    assert set(rows) == {(c, m, s) for c in ("mcap", "ros1") for m in ("compressed", "raw")
                         for s in ((96, 96), (84, 84))}
    for (container, message, size), row in rows.items():
        assert row["frames"] == 161 and row["decode_fps"] > 0 and row["reader_fps"] > 0
        assert row["reader_ratio"] == pytest.approx(row["reader_fps"] / row["decode_fps"])
        assert row["workers_fps"] is None
        err = row["pixel_error"]
        if message == "raw":
            assert err == {"max": 0, "mean": 0.0}, (container, size)
        else:  # JPEG at quality 90 of Push-T's flat colours: about one grey level on average
            assert 0 < err["mean"] < 2, (container, size)
    assert result["lowest_ratio"]["reader"] == min(row["reader_ratio"] for row in rows.values())
    kept = tmp_path / "pusht_bags_161f_q90"
    assert sorted(p.name for p in kept.iterdir()) == sorted(result["recordings"]) == [
        "pusht_compressed.bag", "pusht_compressed_mcap", "pusht_raw.bag", "pusht_raw_mcap"]


def test_image_ingest_unknown_recording_lists_the_known_ones(tmp_path):
    with pytest.raises(SefaInputError, match="mcap/compressed, mcap/raw, ros1/compressed, "
                                             "ros1/raw"):
        image_ingest_throughput(tmp_path, only=["ros2/raw"])


def test_cli_json(shared_data):
    result = CliRunner().invoke(bench_app, ["data", "--data", str(shared_data), "--only",
                                            "kuka_ros1", "--repeat", "1", "--json"])
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)
    assert set(data) == {"machine", "ingest", "images", "sampler"}
    assert data["machine"]["cores"] >= 1
    assert [row["name"] for row in data["ingest"]["rows"]] == ["kuka_ros1"]
    assert data["ingest"]["rows"][0]["ratio_ram"] > 0
    assert data["sampler"] is None  # the sampler needs Push-T, which was not asked for
    assert data["images"] is None  # nor were the camera bags


def test_cli_table(shared_data):
    result = CliRunner().invoke(bench_app, ["data", "--data", str(shared_data), "--only",
                                            "kuka_ros1", "--repeat", "1"])
    assert result.exit_code == 0, result.output
    assert "machine" in result.stdout and "cores" in result.stdout
    assert "KUKA ROS1 bag" in result.stdout and "lowest ratio" in result.stdout


def test_cli_table_with_the_sampler(small_pusht):
    """`--only pusht` measures the sampler too, on a store ingested from the data folder."""
    result = CliRunner().invoke(bench_app, ["data", "--data", str(small_pusht), "--only", "pusht",
                                            "--repeat", "1", "--seconds", "0.1"])
    assert result.exit_code == 0, result.output
    assert "Push-T zarr" in result.stdout and "sampler throughput" in result.stdout
    assert "batch() / window()" in result.stdout and "image cache" in result.stdout


def test_cli_images_table(shared_data):
    result = CliRunner().invoke(bench_app, ["data", "--data", str(shared_data), "--only",
                                            "images", "--image-frames", "100", "--repeat", "1"])
    assert result.exit_code == 0, result.output
    assert "image ingest against decoding alone" in result.stdout
    assert "ROS 1 bag raw" in result.stdout and "lowest ratio (ingest / decoding)" in result.stdout


def test_cli_unknown_recording_lists_images_too(tmp_path):
    result = CliRunner().invoke(bench_app, ["data", "--data", str(tmp_path), "--only", "imgs"])
    assert isinstance(result.exception, SefaInputError)
    assert "kuka_ros1, kuka_mcap, pusht, images" in result.exception.line()


def test_cli_missing_data_dir(tmp_path):
    result = CliRunner().invoke(bench_app, ["data", "--data", str(tmp_path / "nope"), "--json"])
    assert isinstance(result.exception, SefaInputError)
    assert str(tmp_path / "nope") in result.exception.line()
