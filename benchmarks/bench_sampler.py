"""Sampler throughput on Push-T: `batch()` against `window()` one by one, in windows/s.

    python benchmarks/bench_sampler.py [STORE] [--batch 256] [--seconds 3]

STORE is an ingested episode store; by default ../shared/data/pusht_cchi_v7_replay.zarr is
ingested into a temporary directory (on /dev/shm when there is one) and removed afterwards.
Windows follow Diffusion Policy's Push-T config: horizon 16, 2 observation steps, 8 action
steps. Indices are drawn uniformly at random, as a shuffled loader would, so image reads mostly
miss the frame cache (4,096 of 25,650 frames). Prints numbers only; nothing is asserted.
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time
from pathlib import Path
from typing import Callable

import numpy as np

from sefa_data.ingest import IngestOptions, ingest
from sefa_data.sampler import SequenceSampler, to_torch
from sefa_data.zarr_store import EpisodeStore

PUSHT = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "pusht_cchi_v7_replay.zarr"
LOWDIM = ["keypoint", "state"]


def rate(step: Callable[[], int], seconds: float) -> float:
    """Windows per second of `step` (which returns how many windows it produced)."""
    step()  # warm-up: first-touch allocations, imports
    n, start = 0, time.perf_counter()
    while (elapsed := time.perf_counter() - start) < seconds:
        n += step()
    return n / elapsed


def batch_step(s: SequenceSampler, size: int, rng: np.random.Generator, torch_too: bool = False):
    def step() -> int:
        b = s.batch(rng.integers(0, len(s), size))
        if torch_too:
            to_torch(b, "cpu", s.image_keys)
        return size
    return step


def window_step(s: SequenceSampler, size: int, rng: np.random.Generator):
    def step() -> int:
        for i in rng.integers(0, len(s), size):
            s.window(int(i))
        return size
    return step


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("store", nargs="?", type=Path, help="an ingested store (default: Push-T)")
    ap.add_argument("--batch", type=int, default=256)
    ap.add_argument("--seconds", type=float, default=3.0, help="time per measurement")
    args = ap.parse_args()

    tmp = None
    if args.store is None:
        shm = Path("/dev/shm")
        tmp = Path(tempfile.mkdtemp(dir=shm if shm.is_dir() and os.access(shm, os.W_OK) else None))
        args.store = tmp / "pusht.zarr"
        t = time.perf_counter()
        ingest([PUSHT], args.store, IngestOptions(fps=10))
        print(f"ingested {PUSHT.name} into {args.store} in {time.perf_counter() - t:.1f} s")
    try:
        store = EpisodeStore.open(args.store)
        rng = np.random.default_rng(0)
        low = SequenceSampler(store, 16, 2, 8, obs_keys=LOWDIM)
        img = SequenceSampler(store, 16, 2, 8, obs_keys=["img", *LOWDIM])
        through_zarr = SequenceSampler(store, 16, 2, 8, obs_keys=["img", *LOWDIM])
        through_zarr._images["img"]._chunk_file = None  # the generic zarr read, for comparison
        print(f"{len(low)} training windows, horizon 16, n_obs_steps 2, n_action_steps 8, "
              f"batch {args.batch}")
        b = args.batch
        rows = [
            ("low-dim  (keypoint, state, action)  batch()", batch_step(low, b, rng)),
            ("low-dim  (keypoint, state, action)  window()", window_step(low, b, rng)),
            ("images   (img + low-dim)            batch()", batch_step(img, b, rng)),
            ("images   (img + low-dim)  batch() + to_torch", batch_step(img, b, rng, True)),
            ("images   (img + low-dim)            window()", window_step(img, b, rng)),
            ("images, read through zarr           batch()", batch_step(through_zarr, b, rng)),
        ]
        results = [(name, rate(step, args.seconds)) for name, step in rows]
        for name, r in results:
            print(f"{name:48s} {r:12,.0f} windows/s")
        print(f"batch() / window(): low-dim {results[0][1] / results[1][1]:.0f}x, "
              f"images {results[2][1] / results[4][1]:.1f}x")
        cache = img._images["img"]
        print(f"image cache: {len(cache)} frames held, hit rate "
              f"{cache.hits / max(1, cache.hits + cache.misses):.0%}")
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
