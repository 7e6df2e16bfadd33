"""Ingest throughput against the raw read rate of the same file, in one process.

    python benchmarks/bench_ingest.py [--data ../shared/data] [--repeat 3] [--json]

For each recording it times (a) the reader library alone reading and decoding every message or
frame (rosbags AnyReader + deserialize for the KUKA bag; a plain zarr read of every array for
Push-T) and (b) our whole `ingest` into a fresh store (hashing, selection, resampling,
validation, compression and writing included), and prints messages/s for both and their ratio.
The goal of issue 2 is a ratio of at least 0.6. Medians over --repeat runs.

The store is written twice: to a RAM-backed tmpfs (/dev/shm), which measures our code against
the reader on equal terms (the source is read from the page cache), and to the disk (--disk-dir,
default the system temp dir), which adds the file system's cost of creating one file per image
frame (Push-T: 25,650 files; on a small VM this alone varies from 2 to 12 s between runs).
"""

from __future__ import annotations

import argparse
import json
import platform
import shutil
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from sefa_data.ingest import IngestOptions, ingest

JOINTS = ", ".join(f"lwr_arm_{i}_joint" for i in range(7))
KUKA_MAP = f"""
fps: 100
features:
  observation.joint_pos: {{topic: /joint_states, field: "position[{JOINTS}]"}}
  observation.joint_vel: {{topic: /joint_states, field: "velocity[{JOINTS}]"}}
  action: {{topic: /joint_states, field: "effort[{JOINTS}]"}}
"""


def raw_rosbags(path: Path) -> int:
    from rosbags.highlevel import AnyReader

    n = 0
    with AnyReader([path]) as reader:
        for conn, _, raw in reader.messages():
            reader.deserialize(raw, conn.msgtype)
            n += 1
    return n


def raw_zarr(path: Path) -> int:
    import zarr

    root = zarr.open_group(str(path), mode="r")
    frames = 0
    for key in root["data"].array_keys():
        a = root["data"][key][:]
        frames = len(a)
    return frames


def ours(path: Path, options: IngestOptions, out: Path) -> None:
    ingest([path], out, options)


def timed(fn, repeat: int, before=lambda: None) -> tuple[float, object]:
    """Median wall time of `fn` over `repeat` runs; `before` runs untimed ahead of each."""
    times, result = [], None
    for _ in range(repeat):
        before()
        t = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times), result


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "data")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--disk-dir", type=Path, default=Path(tempfile.gettempdir()))
    args = ap.parse_args()
    if not args.data.is_dir():
        raise SystemExit(f"no recordings at {args.data}")

    rows = []
    shm = Path("/dev/shm") if Path("/dev/shm").is_dir() else None
    with tempfile.TemporaryDirectory() as tmp, \
            tempfile.TemporaryDirectory(dir=shm) as ram, \
            tempfile.TemporaryDirectory(dir=args.disk_dir) as disk:
        work = Path(tmp)
        (work / "kuka.yaml").write_text(KUKA_MAP)
        cases = [
            ("KUKA ROS1 bag (4101 msgs)", args.data / "kuka_lwr_honeypot_joint_states.bag",
             raw_rosbags, IngestOptions(topic_map=str(work / "kuka.yaml"))),
            ("KUKA ROS2 MCAP (4101 msgs)", args.data / "kuka_lwr_honeypot_ros2_mcap",
             raw_rosbags, IngestOptions(topic_map=str(work / "kuka.yaml"))),
            ("Push-T zarr (25650 frames, images)", args.data / "pusht_cchi_v7_replay.zarr",
             raw_zarr, IngestOptions(fps=10)),
        ]
        for name, path, raw_fn, options in cases:
            raw_fn(path)  # warm the page cache and imports once for both sides
            t_raw, n = timed(lambda: raw_fn(path), args.repeat)
            row = {"input": name, "messages": n, "raw_s": t_raw, "raw_msgs_per_s": n / t_raw}
            for where, base in (("ram", Path(ram)), ("disk", Path(disk))):
                out = base / "bench.zarr"
                t, _ = timed(lambda: ours(path, options, out), args.repeat,
                             before=lambda: shutil.rmtree(out, ignore_errors=True))
                row.update({f"ours_{where}_s": t, f"ours_{where}_msgs_per_s": n / t,
                            f"ratio_{where}": t_raw / t})
            rows.append(row)
    machine = f"{platform.processor() or platform.machine()}, {__import__('os').cpu_count()} cores, Python {platform.python_version()}"
    if args.json:
        print(json.dumps({"machine": machine, "repeat": args.repeat, "rows": rows}, indent=2))
        return
    print(f"ingest throughput vs raw reader ({machine}; median of {args.repeat})")
    print(f"{'input':36s} {'raw msg/s':>10s} {'ours->RAM':>10s} {'ratio':>6s} {'ours->disk':>11s} {'ratio':>6s}")
    for r in rows:
        print(f"{r['input']:36s} {r['raw_msgs_per_s']:10.0f} {r['ours_ram_msgs_per_s']:10.0f} "
              f"{r['ratio_ram']:6.2f} {r['ours_disk_msgs_per_s']:11.0f} {r['ratio_disk']:6.2f}")
    for where in ("ram", "disk"):
        worst = float(np.min([r[f"ratio_{where}"] for r in rows]))
        print(f"lowest ratio, store in {where}: {worst:.2f} (goal >= 0.60)")


if __name__ == "__main__":
    main()
