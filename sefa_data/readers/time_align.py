"""Timestamped streams to fixed-rate episodes: validate, segment, trim, resample.

Every episode is put on one grid ``t_k = start + k / fps``. Per key, a sample is taken from its
stream with the key's policy:

- ``hold``: the latest sample at or before ``t`` (causal, never leaks the future; the default),
- ``nearest``: the closest sample, which must lie within the key's tolerance,
- ``linear``: linear interpolation between the two neighbours (low-dimensional values only;
  quaternions are interpolated componentwise, which is fine at recording rates).

The episode is trimmed to the span in which every required key has data. Optional keys that
start late are back-filled with their first sample.
"""

from __future__ import annotations

import numpy as np

from sefa_data.episode import Episode, Stream
from sefa_data.errors import SefaInputError
from sefa_data.stats import first_nonfinite
from sefa_data.readers.topic_map import FeatureSpec, TopicMap
from sefa_data.validate import lossy_cast


def _at(times_ns: np.ndarray, i: int) -> str:
    return f"message {i}, t={times_ns[i] / 1e9:.6f} s"


def check_stream(stream: Stream, file: str) -> None:
    """Empty, non-monotonic or non-finite samples are errors naming the key and the sample."""
    key = f"{stream.key} ({stream.topic})"
    if len(stream) == 0:
        raise SefaInputError("no samples: the topic is silent", file=file, key=key)
    if len(stream.values) != len(stream):
        raise SefaInputError(f"{len(stream.values)} values for {len(stream)} timestamps",
                             file=file, key=key)
    back = np.flatnonzero(np.diff(stream.times_ns) < 0)
    if back.size:
        i = int(back[0]) + 1
        raise SefaInputError(
            f"timestamps go backwards by {(stream.times_ns[i - 1] - stream.times_ns[i]) / 1e9:.6f} s",
            file=file, key=key, where=_at(stream.times_ns, i))
    bad = first_nonfinite(stream.values)
    if bad is not None:
        raise SefaInputError("NaN or Inf value", file=file, key=key, where=_at(stream.times_ns, bad))


def check_clock_skew(stream: Stream, limit_s: float | None, file: str) -> None:
    """Header stamps on another clock than the recorder's (sim time, an unsynced robot PC)."""
    if limit_s is None or stream.log_times_ns is None:
        return
    skew = (stream.times_ns - stream.log_times_ns) / 1e9
    over = np.abs(skew) > limit_s
    if over.any():
        i = int(np.argmax(over))  # the first message past the limit
        raise SefaInputError(
            f"header stamps differ from log time by {skew[i]:+.3f} s (limit {limit_s:g} s); "
            "use `stamp: log`, or raise or null `max_stamp_skew_s` if the clocks are meant to differ",
            file=file, key=f"{stream.key} ({stream.topic})", where=_at(stream.times_ns, i))


def segment_bounds(times_ns: np.ndarray, gap_s: float | None,
                   markers_ns: np.ndarray | None) -> list[tuple[int, int]]:
    """(start, end) time spans of the episodes in a recording whose sample times are `times_ns`.

    A new episode starts after a silence longer than `gap_s` and at each marker message.
    """
    times = np.sort(times_ns)
    cuts: list[int] = []
    if gap_s is not None:
        gaps = np.flatnonzero(np.diff(times) > gap_s * 1e9)
        cuts += [int(times[g + 1]) for g in gaps]
    if markers_ns is not None and len(markers_ns):
        cuts += [int(m) for m in markers_ns if times[0] < m <= times[-1]]
    edges = sorted(set(cuts))
    starts = [int(times[0])] + edges
    ends = edges + [int(times[-1]) + 1]  # exclusive
    return [(s, e) for s, e in zip(starts, ends) if e > s]


def grid(start_ns: int, end_ns: int, fps: float) -> np.ndarray:
    """Frame times from start to end inclusive, computed without accumulating rounding error."""
    n = int(np.floor((end_ns - start_ns) * fps / 1e9 + 1e-9)) + 1
    return start_ns + np.round(np.arange(n) * (1e9 / fps)).astype(np.int64)


def resample(times_ns: np.ndarray, values: np.ndarray, t: np.ndarray, policy: str,
             tolerance_ns: float) -> np.ndarray:
    """Values of one stream at the grid times `t` (all within or after the stream's span)."""
    if policy == "linear":
        flat = values.reshape(len(values), -1).astype(np.float64)
        x = (times_ns - times_ns[0]).astype(np.float64)
        xt = (t - times_ns[0]).astype(np.float64)
        out = np.stack([np.interp(xt, x, flat[:, d]) for d in range(flat.shape[1])], axis=1)
        return out.reshape((len(t),) + values.shape[1:])
    # `side="right"` makes hold pick the last of several samples sharing one stamp.
    idx = np.searchsorted(times_ns, t, side="right") - 1
    if policy == "nearest":
        nxt = np.minimum(idx + 1, len(times_ns) - 1)
        prev = np.maximum(idx, 0)
        use_next = np.abs(times_ns[nxt] - t) < np.abs(t - times_ns[prev])
        idx = np.where(use_next | (idx < 0), nxt, prev)
        far = np.abs(times_ns[idx] - t) > tolerance_ns
        if far.any():
            k = int(np.argmax(far))
            raise ValueError(f"no sample within {tolerance_ns / 1e9:g} s of frame {k} "
                             f"(t={t[k] / 1e9:.6f} s; nearest is {abs(times_ns[idx[k]] - t[k]) / 1e9:.3f} s away)")
    return values[np.maximum(idx, 0)]


def _cast(values: np.ndarray, spec: FeatureSpec, key: str, source: str) -> np.ndarray:
    if spec.dtype:
        target = np.dtype(spec.dtype)
        if not spec.allow_lossy_cast:
            # float to an integer type drops fractions even when this recording has none
            kind_loss = values.dtype.kind == "f" and target.kind in "iub"
            changed = lossy_cast(values, target)
            if kind_loss or changed:
                detail = changed or f"{values.dtype} values would lose their fractions"
                raise SefaInputError(f"dtype {target} cannot hold these values: {detail}; set "
                                     "allow_lossy_cast: true if that is meant", file=source,
                                     key=f"{key} ({spec.topic})")
        with np.errstate(all="ignore"):
            return values.astype(target, copy=False)
    if spec.is_image:
        return values.astype(np.uint8, copy=False)
    return values.astype(np.float32, copy=False)


def align_streams(streams: dict[str, Stream], tmap: TopicMap, source: str,
                  markers_ns: np.ndarray | None = None) -> list[Episode]:
    """Validated, segmented, trimmed fixed-rate episodes from one recording's streams."""
    for key, spec in tmap.features.items():
        if key not in streams and not spec.optional:
            raise SefaInputError("required key has no stream", file=source, key=f"{key} ({spec.topic})")
    for key, stream in streams.items():
        check_stream(stream, source)
        if tmap.stamp_of(tmap.features[key]) != "log":
            check_clock_skew(stream, tmap.max_stamp_skew_s, source)

    required = [k for k in streams if not tmap.features[k].optional]
    all_times = np.concatenate([streams[k].times_ns for k in required])
    episodes = []
    for n, (seg_start, seg_end) in enumerate(segment_bounds(all_times, tmap.split.gap_s, markers_ns)):
        parts = {}
        for key, s in streams.items():
            keep = (s.times_ns >= seg_start) & (s.times_ns < seg_end)
            parts[key] = (s.times_ns[keep], s.values[keep])
        label = f"segment {n}"
        empty = [k for k in required if len(parts[k][0]) == 0]
        if empty:
            raise SefaInputError("no samples in this segment", file=source, key=empty[0],
                                 where=f"{label}, t={seg_start / 1e9:.6f} s")
        start = max(int(parts[k][0][0]) for k in required)
        end = min(int(parts[k][0][-1]) for k in required)
        t = grid(start, end, tmap.fps) if end >= start else np.zeros(0, np.int64)
        if len(t) < tmap.min_length:
            raise SefaInputError(
                f"only {len(t)} frames where all required keys have data (min_length {tmap.min_length})",
                file=source, key=None, where=f"{label}, t={seg_start / 1e9:.6f} s")
        data = {}
        for key, (times, values) in parts.items():
            spec = tmap.features[key]
            if len(times) == 0:
                continue  # an optional key silent in this segment
            try:
                out = resample(times, values, t, spec.resample, tmap.tolerance_of(spec) * 1e9)
            except ValueError as e:
                raise SefaInputError(str(e), file=source, key=f"{key} ({spec.topic})",
                                     where=label) from None
            data[key] = _cast(out, spec, key, source)
        names = {k: s.names for k, s in streams.items() if s.names and k in data}
        episodes.append(Episode(data=data, source=source, start_time_ns=int(t[0]), names=names,
                                label=label))
    return episodes
