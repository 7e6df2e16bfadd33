"""Ingest throughput against the raw read rate of the same file, in one process.

    python benchmarks/bench_ingest.py [--data ../shared/data] [--repeat 3] [--json]
                                      [--disk-dir DIR] [--only kuka_ros1 ...]

For each recording it times (a) the reader library alone reading and decoding every message or
frame (rosbags AnyReader + deserialize for the KUKA bag; a plain zarr read of every array for
Push-T) and (b) our whole `ingest` into a fresh store (hashing, selection, resampling,
validation, compression and writing included), and prints messages/s for both and their ratio.
The goal of issue 2 is a ratio of at least 0.6. Medians over --repeat runs.

The store is written twice: to a RAM-backed tmpfs (/dev/shm), which measures our code against
the reader on equal terms (the source is read from the page cache), and to the disk (--disk-dir,
default the system temp dir), which adds the file system's cost of creating one file per image
frame (Push-T: 25,650 files; on a small VM this alone varies from 2 to 12 s between runs).

The measuring code is `sefa_data.bench.throughput.ingest_throughput` (also `sefa bench data`).
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

from sefa_data.errors import SefaInputError
from sefa_data.bench.throughput import (
    DEFAULT_DATA_DIR,
    RECORDING_NAMES,
    ingest_throughput,
    machine_description,
    machine_summary,
)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA_DIR)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--disk-dir", type=Path, default=Path(tempfile.gettempdir()))
    ap.add_argument("--only", action="append", choices=RECORDING_NAMES,
                    help="only this recording (repeatable; default all)")
    args = ap.parse_args()
    try:
        result = ingest_throughput(args.data, repeat=args.repeat, disk_dir=args.disk_dir,
                                   only=args.only)
    except SefaInputError as e:
        raise SystemExit(f"error: {e.line()}")
    rows = result["rows"]
    machine = machine_summary(machine_description())
    if args.json:
        print(json.dumps({"machine": machine, "repeat": args.repeat, "rows": rows}, indent=2))
        return
    print(f"ingest throughput vs raw reader ({machine}; median of {args.repeat})")
    print(f"{'input':36s} {'raw msg/s':>10s} {'ours->RAM':>10s} {'ratio':>6s} {'ours->disk':>11s} {'ratio':>6s}")
    for r in rows:
        print(f"{r['input']:36s} {r['raw_msgs_per_s']:10.0f} {r['ours_ram_msgs_per_s']:10.0f} "
              f"{r['ratio_ram']:6.2f} {r['ours_disk_msgs_per_s']:11.0f} {r['ratio_disk']:6.2f}")
    for where in ("ram", "disk"):
        print(f"lowest ratio, store in {where}: {result['lowest_ratio'][where]:.2f} "
              f"(goal >= {result['goal']:.2f})")


if __name__ == "__main__":
    main()
