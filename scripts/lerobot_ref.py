"""A reference for `scripts/lerobot_check.py DIR --ref REF.npz` (run with LeRobot 0.6.1's
Python): what LeRobot should return for a sefa store converted with `sefa convert STORE --to
lerobot --out DIR`.

    python scripts/lerobot_ref.py STORE REF.npz

Arrays are named after the features, one row per frame as LeRobot's __getitem__ gives them:
low-dim keys flattened to vectors (a one-value key as a scalar), images uint8 HWC; plus
`episode_ends`. LeRobot 0.6.1's loader hands float64 features out as float32 (it makes torch
tensors of the parquet's Python floats, torch's default dtype), so float64 keys are given as
float32 here; the parquet itself keeps the float64 values (`sefa ingest` reads them back
exactly). Low-dim values must then match exactly, images within the codec's loss.
"""
import sys

import numpy as np

from sefa_data.store.zarr_store import EpisodeStore


def main(store_path: str, out: str) -> None:
    store = EpisodeStore.open(store_path)
    arrays = {"episode_ends": store.episode_ends}
    for key, f in store.attrs["features"].items():
        values = store.root["data"][key][:]
        if f["type"] != "image":
            values = values.reshape(len(values), -1)
            values = values[:, 0] if values.shape[1] == 1 else values
            values = values.astype(np.float32) if values.dtype == np.float64 else values
        arrays[key] = values
    np.savez(out, **arrays)
    print(f"wrote {out}: {', '.join(f'{k} {v.shape}' for k, v in arrays.items())}")


if __name__ == "__main__":
    main(*sys.argv[1:3])
