"""What the store's integrity checks cost on open, against the open itself and the ingest.

    PYTHONPATH=. python benchmarks/bench_store_verify.py [--data ../shared/data] [--repeat 5]

Ingests Push-T (206 episodes, 25,650 frames, one chunk file per image frame) into a fresh store,
then times `EpisodeStore.open` with verify="none" (the zarr open alone), "quick" (what every
open does: attributes, the episode index, presence and size of every file, checksums of all but
the image chunks) and "full" (every checksum: `sefa inspect --verify`, and training's open).
Prints the median seconds of --repeat opens (the page cache is warm after the first) and their
ratios to the plain open and to the ingest.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

from sefa_data.ingest import IngestOptions, ingest
from sefa_data.bench.throughput import DEFAULT_DATA_DIR
from sefa_data.store.zarr_store import EpisodeStore


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA_DIR)
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        store = Path(tmp) / "pusht.zarr"
        t = time.perf_counter()
        ingest([args.data / "pusht_cchi_v7_replay.zarr"], store,
               IngestOptions(fps=10, renames={"img": "observation.images.top"}))
        ingest_s = time.perf_counter() - t
        times = {}
        for level in ("none", "quick", "full"):
            runs = []
            for _ in range(args.repeat):
                t = time.perf_counter()
                s = EpisodeStore.open(store, verify=level)
                runs.append(time.perf_counter() - t)
            times[level] = statistics.median(runs)
            info = s.verification
        files = sum(1 for p in store.rglob("*") if p.is_file())
        size = sum(p.stat().st_size for p in store.rglob("*") if p.is_file())
    print(f"Push-T store: {files} files, {size / 2**20:.0f} MiB; ingest {ingest_s:.1f} s; "
          f"median of {args.repeat} opens")
    print(f"{'verify':8s} {'seconds':>8s} {'x plain open':>12s} {'% of ingest':>12s}")
    for level, sec in times.items():
        print(f"{level:8s} {sec:8.3f} {sec / times['none']:12.1f} {100 * sec / ingest_s:11.1f}%")
    print(f"full check hashed {info['files_hashed']} files")


if __name__ == "__main__":
    main()
