"""What is in a store, as one JSON-ready dict (`sefa inspect` renders it as tables)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sefa_data.store.zarr_store import EpisodeStore


def store_summary(path: str | Path, verify: bool = False) -> dict:
    """`verify` checks every checksum (image chunks too); without it, the open's quick check."""
    store = EpisodeStore.open(path, verify="full" if verify else "quick")
    attrs = store.attrs
    lengths = store.episode_lengths
    starts = store.root["meta"]["episode_start_time_ns"][:]
    source_of = store.root["meta"]["episode_source"][:]
    sources = attrs["sources"]
    masks = {name: store.mask(name) for name in store.mask_names()}
    return {
        "path": str(store.path),
        "sefa_format": attrs["sefa_format"],
        "fps": store.fps,
        "n_episodes": store.n_episodes,
        "n_frames": store.n_frames,
        "episode_length": {"min": int(lengths.min()), "max": int(lengths.max()),
                           "mean": float(lengths.mean())} if len(lengths) else {},
        "features": {k: {**f, "stats": attrs["stats"].get(k)} for k, f in attrs["features"].items()},
        "masks": {name: int(m.sum()) for name, m in masks.items()},
        "episodes": [
            {"index": i, "length": int(lengths[i]), "source": sources[source_of[i]]["path"],
             "start_time_ns": int(starts[i]),
             "masks": [n for n, m in masks.items() if m[i]]}
            for i in range(store.n_episodes)
        ],
        "sources": [{k: s[k] for k in ("path", "sha256", "size", "format", "episodes")}
                    for s in sources],
        "versions": attrs.get("versions", {}),
        "integrity": store.verification,
    }


def constant_dims(stats: dict | None) -> list[int]:
    if not stats:
        return []
    return [int(i) for i in np.flatnonzero(np.asarray(stats["constant"]).reshape(-1))]
