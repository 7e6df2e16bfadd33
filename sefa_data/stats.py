"""Per-key statistics: min, max, mean, std, q01, q99, with constant dimensions flagged.

Low-dimensional keys get exact statistics per element of the frame shape. Images get them per
channel from a 256-bin histogram, which is exact for uint8 and can be summed across appends, so
adding episodes never rereads the images already in the store.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

# A dimension is constant when its range is below this, relative to its magnitude; the
# normalizer must not divide by such a range (Diffusion Policy uses range_eps = 1e-4).
CONSTANT_RTOL = 1e-6


@dataclass
class KeyStats:
    count: int
    min: np.ndarray
    max: np.ndarray
    mean: np.ndarray
    std: np.ndarray
    q01: np.ndarray
    q99: np.ndarray

    @property
    def constant(self) -> np.ndarray:
        scale = np.maximum(1.0, np.maximum(np.abs(self.min), np.abs(self.max)))
        return (self.max - self.min) <= CONSTANT_RTOL * scale

    def to_json(self) -> dict:
        out = {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in asdict(self).items()}
        out["constant"] = self.constant.tolist()
        return out


def first_nonfinite(values: np.ndarray) -> int | None:
    """Index of the first row (frame, step, message) holding a NaN or Inf; None when all are
    finite or the dtype cannot hold them."""
    if values.dtype.kind not in "fc" or len(values) == 0:
        return None
    finite = np.isfinite(values.reshape(len(values), -1)).all(axis=1)
    return None if finite.all() else int(np.argmin(finite))


def lowdim_stats(values: np.ndarray) -> KeyStats:
    x = values.astype(np.float64, copy=False)
    q01, q99 = np.quantile(x, [0.01, 0.99], axis=0)
    return KeyStats(count=len(x), min=x.min(0), max=x.max(0), mean=x.mean(0), std=x.std(0),
                    q01=q01, q99=q99)


def image_histogram(images: np.ndarray) -> np.ndarray:
    """(C, 256) counts of each uint8 value per channel of (N, H, W, C) images."""
    flat = images.reshape(-1, images.shape[-1])
    return np.stack([np.bincount(flat[:, c], minlength=256) for c in range(flat.shape[1])]
                    ).astype(np.int64)


def stats_from_histogram(hist: np.ndarray) -> KeyStats:
    values = np.arange(256, dtype=np.float64)
    total = hist.sum(1)
    mean = (hist * values).sum(1) / total
    std = np.sqrt((hist * (values - mean[:, None]) ** 2).sum(1) / total)
    cdf = np.cumsum(hist, 1) / total[:, None]
    nonzero = hist > 0

    def quantile(q: float) -> np.ndarray:
        # the 'lower' quantile of the discrete distribution, as np.quantile(method="lower") gives
        return np.array([np.searchsorted(c, q * (1 - 1e-12)) for c in cdf], dtype=np.float64)

    return KeyStats(count=int(total[0]) if len(total) else 0,
                    min=np.array([np.flatnonzero(r)[0] for r in nonzero], np.float64),
                    max=np.array([np.flatnonzero(r)[-1] for r in nonzero], np.float64),
                    mean=mean, std=std, q01=quantile(0.01), q99=quantile(0.99))
