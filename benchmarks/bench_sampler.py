"""Sampler throughput on Push-T: `batch()` against `window()` one by one, in windows/s.

    python benchmarks/bench_sampler.py [STORE] [--batch 256] [--seconds 3]

STORE is an ingested episode store; by default ../shared/data/pusht_cchi_v7_replay.zarr is
ingested into a temporary directory (on /dev/shm when there is one) and removed afterwards.
Windows follow Diffusion Policy's Push-T config: horizon 16, 2 observation steps, 8 action
steps. Indices are drawn uniformly at random, as a shuffled loader would, so image reads mostly
miss the frame cache (4,096 of 25,650 frames). Prints numbers only; nothing is asserted.

The measuring code is `sefa_data.bench.throughput.sampler_throughput` (also `sefa bench data`).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from sefa_data.errors import SefaInputError
from sefa_data.bench.throughput import sampler_throughput


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("store", nargs="?", type=Path, help="an ingested store (default: Push-T)")
    ap.add_argument("--batch", type=int, default=256)
    ap.add_argument("--seconds", type=float, default=3.0, help="time per measurement")
    args = ap.parse_args()
    try:
        result = sampler_throughput(args.store, batch=args.batch, seconds=args.seconds, log=print)
    except SefaInputError as e:
        raise SystemExit(f"error: {e.line()}")
    for row in result["rows"]:
        print(f"{row['label']:48s} {row['windows_per_s']:12,.0f} windows/s")
    ratio = result["batch_over_window"]
    images = "" if ratio["images"] is None else f", images {ratio['images']:.1f}x"
    print(f"batch() / window(): low-dim {ratio['low_dim']:.0f}x{images}")
    cache = result["image_cache"]
    if cache is not None:
        print(f"image cache: {cache['frames']} frames held, hit rate {cache['hit_rate']:.0%}")


if __name__ == "__main__":
    main()
