"""LeRobot's feature statistics: per episode, then aggregated over episodes (compute_stats.py).

Each feature gets min, max, mean, std, count and the quantiles q01, q10, q50, q90, q99. Images
are per channel, scaled to [0, 1], shaped (C, 1, 1), from at most 100 frames of an episode
spread evenly (LeRobot samples frames too); low-dim features are per value over every frame.
The dataset's statistics aggregate the episodes' as LeRobot does: counts add up, means and
quantiles are count-weighted, variances pool the within- and between-episode parts.
"""

from __future__ import annotations

import numpy as np

QUANTILES = {"q01": 0.01, "q10": 0.10, "q50": 0.50, "q90": 0.90, "q99": 0.99}
_IMAGE_SAMPLES = 100
_IMAGE_SIDE = 150  # images larger than this are strided down for their statistics


def lowdim_episode_stats(values: np.ndarray) -> dict[str, np.ndarray]:
    x = values.reshape(len(values), -1).astype(np.float64)
    return _stats(x, axis=0, count=len(x))


def image_episode_stats(frames: np.ndarray) -> dict[str, np.ndarray]:
    """frames (T, H, W, C) uint8 -> statistics of shape (C, 1, 1) in [0, 1].

    From a 256-bin histogram per channel: exact for uint8 and far cheaper than sorting the
    pixels for the quantiles (a quantile is the first grey level whose cumulative count
    reaches it)."""
    pick = np.unique(np.linspace(0, len(frames) - 1, min(len(frames), _IMAGE_SAMPLES)).round()
                     .astype(int))
    step = max(1, max(frames.shape[1:3]) // _IMAGE_SIDE)
    x = frames[pick, ::step, ::step].reshape(-1, frames.shape[-1])
    levels = np.arange(256, dtype=np.float64) / 255.0
    out: dict[str, list] = {k: [] for k in ("min", "max", "mean", "std", *QUANTILES)}
    for c in range(x.shape[1]):
        hist = np.bincount(x[:, c], minlength=256).astype(np.float64)
        p = hist / hist.sum()
        mean = float(p @ levels)
        seen = np.flatnonzero(hist)
        cdf = np.cumsum(p)
        out["min"].append(levels[seen[0]])
        out["max"].append(levels[seen[-1]])
        out["mean"].append(mean)
        out["std"].append(float(np.sqrt(p @ (levels - mean) ** 2)))
        for name, q in QUANTILES.items():
            out[name].append(levels[min(255, int(np.searchsorted(cdf, q)))])
    return {**{k: np.asarray(v).reshape(-1, 1, 1) for k, v in out.items()},
            "count": np.array([len(pick)])}


def _stats(x: np.ndarray, axis: int, count: int) -> dict[str, np.ndarray]:
    qs = np.quantile(x, list(QUANTILES.values()), axis=axis)
    return {"min": x.min(axis), "max": x.max(axis), "mean": x.mean(axis), "std": x.std(axis),
            "count": np.array([count]), **{name: q for name, q in zip(QUANTILES, qs)}}


def aggregate(episodes: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    counts = np.array([float(e["count"][0]) for e in episodes])
    w = counts / counts.sum()

    def weighted(name: str) -> np.ndarray:
        return sum(wi * e[name] for wi, e in zip(w, episodes))

    mean = weighted("mean")
    var = sum(wi * (e["std"] ** 2 + (e["mean"] - mean) ** 2) for wi, e in zip(w, episodes))
    return {"min": np.min([e["min"] for e in episodes], axis=0),
            "max": np.max([e["max"] for e in episodes], axis=0),
            "mean": mean, "std": np.sqrt(var), "count": np.array([int(counts.sum())]),
            **{name: weighted(name) for name in QUANTILES}}


def to_json(stats: dict[str, np.ndarray]) -> dict:
    return {k: np.asarray(v).tolist() for k, v in stats.items()}
