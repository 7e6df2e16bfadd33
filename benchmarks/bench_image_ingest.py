"""Image ingest against decoding alone, on camera recordings made from the Push-T frames.

    python benchmarks/bench_image_ingest.py [--data ../shared/data] [--frames 5000]
                                            [--repeat 3] [--size 96x96 --size 84x84]
                                            [--jpeg-quality 90] [--decode-workers N]
                                            [--only ros1/compressed ...] [--work DIR] [--json]

No real recording with camera images is public (../shared/data/MANIFEST.md), so the first
Push-T episodes (at least --frames frames) are written, with rosbags' own writers, as a ROS 2
bag with MCAP storage and as a ROS 1 bag, each once with sensor_msgs/CompressedImage (JPEG at
--jpeg-quality) and once with raw sensor_msgs/Image (rgb8), beside the agent state and action
(`sefa_data.bench.pusht_bags`). For each recording it times (a) decoding alone: rosbags reading
every image message and sefa's decoder turning it into an RGB uint8 array, one by one, and (b) our
whole `ingest` into a fresh store in RAM (/dev/shm when there is one) at each --size, once with
the reader decoding the images and once with --decode-workers processes decoding beside it. It
prints frames/s and the ratios ingest / decoding; issue 14's goal is a ratio of at least 0.6.
Medians over --repeat runs. Each store is then checked against the source frames (pixel
error: 0 for raw images; the workers' frames must equal the reader's).

The recordings are kept in --work DIR for later runs (default: a temporary folder, removed).
The measuring code is `sefa_data.bench.throughput.image_ingest_throughput` (also `sefa bench data`).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from sefa_data.errors import SefaInputError
from sefa_data.bench.throughput import (
    DEFAULT_DATA_DIR,
    IMAGE_RECORDINGS,
    IMAGE_SIZES,
    image_ingest_throughput,
    machine_description,
    machine_summary,
)


def size(text: str) -> tuple[int, int]:
    try:
        height, width = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected HEIGHTxWIDTH, e.g. 84x84, got {text!r}")
    return height, width


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA_DIR)
    ap.add_argument("--frames", type=int, default=5000,
                    help="at least this many Push-T frames (whole episodes from the start)")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--size", type=size, action="append", dest="sizes",
                    help="image_size of the ingest, HEIGHTxWIDTH (repeatable; default 96x96 "
                         "and 84x84)")
    ap.add_argument("--jpeg-quality", type=int, default=90)
    ap.add_argument("--decode-workers", type=int,
                    help="processes decoding beside the reader in the second ingest (default: "
                         "one per CPU less one; 0 skips it)")
    ap.add_argument("--only", action="append", choices=IMAGE_RECORDINGS,
                    help="only this recording, container/message (repeatable; default all)")
    ap.add_argument("--work", type=Path, help="keep the recordings here for later runs")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    try:
        result = image_ingest_throughput(args.data, frames=args.frames, repeat=args.repeat,
                                         sizes=args.sizes or IMAGE_SIZES,
                                         jpeg_quality=args.jpeg_quality,
                                         decode_workers=args.decode_workers, only=args.only,
                                         work_dir=args.work)
    except SefaInputError as e:
        raise SystemExit(f"error: {e.line()}")
    machine = machine_summary(machine_description())
    if args.json:
        print(json.dumps({"machine": machine, **result}, indent=2))
        return
    workers = result["decode_workers"]
    label = f"{workers} worker{'' if workers == 1 else 's'}"
    print(f"image ingest vs decoding alone, frames/s ({machine}; {result['frames']} Push-T "
          f"frames, {result['episodes']} episodes, JPEG quality {result['jpeg_quality']}; "
          f"median of {result['repeat']})")
    print(f"{'recording':24s} {'size':>5s} {'decode':>7s} {'ingest':>7s} {'ratio':>5s} "
          f"{label:>10s} {'ratio':>5s} {'pixel error max/mean':>21s}")
    for r in result["rows"]:
        h, w = r["image_size"]
        err = r["pixel_error"]
        pool = (f"{r['workers_fps']:10.0f} {r['workers_ratio']:5.2f}" if r["workers_fps"]
                else f"{'-':>10s} {'-':>5s}")
        print(f"{r['input']:24s} {h:>2d}x{w:<2d} {r['decode_fps']:7.0f} {r['reader_fps']:7.0f} "
              f"{r['reader_ratio']:5.2f} {pool} {err['max']:>12d} / {err['mean']:.2f}")
    low = result["lowest_ratio"]
    pool = "" if low["workers"] is None else f", with {label} decoding {low['workers']:.2f}"
    print(f"lowest ratio: reader decoding {low['reader']:.2f}{pool} (goal >= {result['goal']:.2f})")


if __name__ == "__main__":
    main()
