"""Training windows over an episode store, with Diffusion Policy's sampling semantics.

A window is `horizon` consecutive frames of one episode. Near an episode's edges a window may
start up to `pad_before` frames before the first frame and end up to `pad_after` frames after
the last; the missing frames repeat the first (or last) frame, as in Diffusion Policy's
`SequenceSampler`. Windows never cross episodes.

Each window has a stable integer index: its row in `create_indices`' output for the store's
episodes, split and sampler settings. Later stages (reflow pairs) record that index.

Two read paths return the same arrays:

* `window(i)` slices the buffer and pads it, DP's way; the reference path.
* `batch(idx)` gathers many windows with one fancy index per key. Edge padding is the same as
  clamping the frame index into the episode, so a (B, horizon) index array does all of it.

Low-dim keys live in memory as numpy. Images are read on demand and kept in a bounded LRU
cache of frames; they stay uint8 HWC until `to_torch`.
"""

from __future__ import annotations

from collections import OrderedDict
from pathlib import Path
from typing import Collection, Literal, NamedTuple

import numpy as np
import torch
import zarr

from sefa_data.errors import SefaInputError
from sefa_data.store.zarr_store import EpisodeStore

Split = Literal["train", "valid"]


def create_indices(episode_ends: np.ndarray, sequence_length: int, pad_before: int = 0,
                   pad_after: int = 0, episode_mask: np.ndarray | None = None) -> np.ndarray:
    """Diffusion Policy's window table, vectorised: (N, 4) int64 rows of
    [buffer_start, buffer_end, sample_start, sample_end].

    `buffer[buffer_start:buffer_end]` holds the real frames of a window, which go to
    `sample[sample_start:sample_end]`; the rest of the sample repeats the edge frames. An
    episode of length L gives max(0, L + pad_before + pad_after - sequence_length + 1)
    windows, in order of start, episodes in store order.
    """
    ends = np.asarray(episode_ends, dtype=np.int64)
    mask = np.ones(len(ends), bool) if episode_mask is None else np.asarray(episode_mask, bool)
    if mask.shape != ends.shape:
        raise ValueError(f"episode_mask has shape {mask.shape}, episode_ends {ends.shape}")
    # DP clamps the padding the same way: more than T-1 would give windows with no real frame.
    pad_before = min(max(pad_before, 0), sequence_length - 1)
    pad_after = min(max(pad_after, 0), sequence_length - 1)

    episode, start = _window_starts(ends, sequence_length, pad_before, pad_after, mask)
    ep_start = _episode_starts(ends)[episode]
    length = (ends - _episode_starts(ends))[episode]
    buffer_start = np.maximum(start, 0) + ep_start
    buffer_end = np.minimum(start + sequence_length, length) + ep_start
    sample_start = buffer_start - (start + ep_start)
    sample_end = sequence_length - ((start + sequence_length + ep_start) - buffer_end)
    return np.stack([buffer_start, buffer_end, sample_start, sample_end], axis=1)


def _episode_starts(ends: np.ndarray) -> np.ndarray:
    return np.concatenate([np.zeros(1, np.int64), ends[:-1]])


def _window_starts(ends: np.ndarray, sequence_length: int, pad_before: int, pad_after: int,
                   mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(episode, start) of every window; `start` is relative to the episode's first frame and
    negative for windows that begin in the front padding."""
    lengths = ends - _episode_starts(ends)
    counts = np.maximum(lengths + pad_before + pad_after - sequence_length + 1, 0) * mask
    episode = np.repeat(np.arange(len(ends), dtype=np.int64), counts)
    first_row = np.repeat(np.cumsum(counts) - counts, counts)
    start = np.arange(len(episode), dtype=np.int64) - first_row - pad_before
    return episode, start


class WindowRef(NamedTuple):
    """Where window i lies: its episode (store index) and its first frame relative to the
    episode start (negative inside the front padding)."""

    episode: int
    start: int


class FrameCache:
    """Reads image frames of one zarr array, keeping the last `capacity` frames used.

    Not thread-safe: give each loader worker its own sampler (forked workers do).
    """

    def __init__(self, array: zarr.Array, directory: Path, capacity: int):
        self.array = array
        self.capacity = max(0, int(capacity))
        self.frame_shape = tuple(array.shape[1:])
        self.dtype = array.dtype
        self.hits = 0
        self.misses = 0
        self._lru: OrderedDict[int, np.ndarray] = OrderedDict()
        self._chunk_file = _chunk_file_template(array, directory)

    def __len__(self) -> int:
        return len(self._lru)

    def __getstate__(self) -> dict:
        # a spawned loader worker starts with an empty cache, not a copy of the parent's
        return {**self.__dict__, "_lru": OrderedDict()}

    def get(self, frames: np.ndarray) -> np.ndarray:
        """The frames at these buffer indices, (len(frames), *frame_shape), in that order."""
        unique, inverse = np.unique(np.asarray(frames, np.int64), return_inverse=True)
        out = np.empty((len(unique),) + self.frame_shape, self.dtype)
        missing = []
        for j, f in enumerate(unique.tolist()):
            hit = self._lru.get(f)
            if hit is None:
                missing.append(j)
            else:
                self._lru.move_to_end(f)
                out[j] = hit
        self.hits += len(unique) - len(missing)
        self.misses += len(missing)
        if missing:
            rows = np.asarray(missing)
            out[rows] = self._read(unique[rows])
            self._remember(unique[rows], out[rows])
        return out[inverse.reshape(-1)]

    def _remember(self, frames: np.ndarray, values: np.ndarray) -> None:
        # only the last `capacity` of a large read can stay anyway
        keep = slice(max(0, len(frames) - self.capacity), None)
        for f, v in zip(frames[keep].tolist(), values[keep]):
            self._lru[f] = v.copy()  # a view would pin the whole batch array in memory
        while len(self._lru) > self.capacity:
            self._lru.popitem(last=False)

    def _read(self, frames: np.ndarray) -> np.ndarray:
        if self._chunk_file is None:
            return self.array.oindex[frames]
        return _read_frame_chunks(self.array, self._chunk_file, frames)


def _chunk_file_template(array: zarr.Array, directory: Path) -> str | None:
    """For a Zarr format 2 array of one-frame chunks on disk, the chunk file name with "{}"
    for the frame index; None for any other layout (read through zarr instead).

    zarr-python 3 spends about 0.4 ms of Python per chunk; decoding the file ourselves with the
    array's own codec costs about 30 us a frame. The store writes images this way too.
    A string rather than a closure, so that a sampler pickles into spawned loader workers.
    """
    meta = array.metadata
    if (meta.zarr_format != 2 or array.chunks[0] != 1 or array.chunks[1:] != array.shape[1:]
            or meta.filters or meta.order != "C" or not directory.is_dir()):
        return None
    sep = meta.dimension_separator
    rest = sep.join("0" for _ in array.shape[1:])
    return str(directory / "{}") + sep + rest


def _read_frame_chunks(array: zarr.Array, template: str, frames: np.ndarray) -> np.ndarray:
    out = np.empty((len(frames),) + tuple(array.shape[1:]), array.dtype)
    codec = array.metadata.compressor
    for j, f in enumerate(frames.tolist()):
        try:
            with open(template.format(f), "rb") as fh:
                raw = fh.read()
        except FileNotFoundError:  # zarr leaves chunks equal to the fill value unwritten
            out[j] = array.metadata.fill_value or 0
            continue
        if codec is None:
            out[j] = np.frombuffer(raw, array.dtype).reshape(out.shape[1:])
        else:
            codec.decode(raw, out=out[j])
    return out


def action_vectors(frames: np.ndarray) -> np.ndarray:
    """Actions (N, ...) as the vectors a policy predicts, (N, Da): an action stored with leading
    axes of size 1 per frame (LeRobot's `[1, 2]`, read as LeRobot reads it) loses them. Any
    other shape is kept; the policy's shapes refuse it (sefa_model's `resolve_shapes`)."""
    if frames.ndim > 2 and all(d == 1 for d in frames.shape[1:-1]):
        return frames.reshape(len(frames), frames.shape[-1])
    return frames


class SequenceSampler:
    """Windows of `horizon` frames from one split of a store, DP-style.

    Observation keys come back for the first `n_obs_steps` frames of a window, the action for
    all `horizon` frames. pad_before = n_obs_steps - 1 and pad_after = n_action_steps - 1, as
    in Diffusion Policy's task configs.
    """

    def __init__(self, store: EpisodeStore, horizon: int, n_obs_steps: int, n_action_steps: int,
                 *, split: Split = "train", obs_keys: list[str] | None = None,
                 action_key: str = "action", image_cache_frames: int = 4096):
        if not (horizon >= 1 and 1 <= n_obs_steps <= horizon and 1 <= n_action_steps <= horizon):
            raise SefaInputError(
                f"need 1 <= n_obs_steps ({n_obs_steps}) <= horizon ({horizon}) and "
                f"1 <= n_action_steps ({n_action_steps}) <= horizon", file=str(store.path))
        features = store.attrs["features"]
        if obs_keys is None:
            obs_keys = [k for k in store.keys if k != action_key]
        if action_key in obs_keys:
            raise SefaInputError("the action key is also an observation key",
                                 file=str(store.path), key=action_key)
        for key in [*obs_keys, action_key]:
            if key not in features:
                raise SefaInputError(f"no such key (store keys: {', '.join(store.keys)})",
                                     file=str(store.path), key=key)
        if split not in store.mask_names():
            raise SefaInputError(f"no split mask mask/{split}", file=str(store.path))

        self.store = store
        self.horizon, self.n_obs_steps, self.n_action_steps = horizon, n_obs_steps, n_action_steps
        self.pad_before, self.pad_after = n_obs_steps - 1, n_action_steps - 1
        self.split = split
        self.obs_keys = list(obs_keys)
        self.action_key = action_key
        self.image_keys = [k for k in self.obs_keys if features[k]["type"] == "image"]
        self.lowdim_keys = [k for k in self.obs_keys if k not in self.image_keys]

        ends = store.episode_ends
        self.episode_mask = store.mask(split).astype(bool)
        if not self.episode_mask.any():
            raise SefaInputError(f"the '{split}' split has no episodes", file=str(store.path))
        self.indices = create_indices(ends, horizon, self.pad_before, self.pad_after,
                                      self.episode_mask)
        if len(self.indices) == 0:
            raise SefaInputError(
                f"no episode of the '{split}' split is long enough for a window of {horizon} "
                f"frames (with {self.pad_before} + {self.pad_after} frames of padding)",
                file=str(store.path))
        self._episode, self._start = _window_starts(
            ends, horizon, self.pad_before, self.pad_after, self.episode_mask)
        self._ep_first = _episode_starts(ends)  # buffer index of each episode's first frame
        self._ep_last = ends - 1

        data = store.root["data"]
        # one read per key: zarr calls are slow, and low-dim data is small
        self._lowdim = {k: data[k][:] for k in [*self.lowdim_keys, action_key]}
        self._lowdim[action_key] = action_vectors(self._lowdim[action_key])
        self._images = {k: FrameCache(data[k], Path(store.path) / "data" / k, image_cache_frames)
                        for k in self.image_keys}

    def __len__(self) -> int:
        return len(self.indices)

    def window_index(self, i: int) -> WindowRef:
        return WindowRef(int(self._episode[i]), int(self._start[i]))

    def frame_indices(self, idx: np.ndarray) -> np.ndarray:
        """(B, horizon) buffer indices of the windows `idx`, edge padding applied.

        Computed per call rather than stored: O(B * horizon) work, no O(N * horizon) table.
        """
        idx = self._check(idx)
        ep = self._episode[idx]
        first = self._ep_first[ep] + self._start[idx]
        frames = first[:, None] + np.arange(self.horizon, dtype=np.int64)
        return np.clip(frames, self._ep_first[ep][:, None], self._ep_last[ep][:, None])

    def batch(self, idx: np.ndarray) -> dict[str, np.ndarray]:
        """Windows `idx`, stacked: obs keys (B, n_obs_steps, ...), action (B, horizon, ...)."""
        frames = self.frame_indices(idx)
        obs_frames = frames[:, :self.n_obs_steps]
        out = {k: self._lowdim[k][obs_frames] for k in self.lowdim_keys}
        for k, cache in self._images.items():
            out[k] = cache.get(obs_frames.reshape(-1)).reshape(obs_frames.shape + cache.frame_shape)
        out[self.action_key] = self._lowdim[self.action_key][frames]
        return out

    def buffer(self, key: str) -> np.ndarray:
        """Every frame of `key` that `batch` gathers from, indexed by `frame_indices`' values:
        low-dim keys from memory, image keys read whole (uint8 HWC; the caller checks that
        they fit where it keeps them)."""
        if key in self._images:
            return self._images[key].array[:]
        return self._lowdim[key]

    def buffer_nbytes(self, key: str) -> int:
        """The bytes `buffer(key)` takes, without reading it."""
        array = self._images[key].array if key in self._images else self._lowdim[key]
        return int(np.prod(array.shape)) * np.dtype(array.dtype).itemsize

    def actions(self, idx: np.ndarray) -> np.ndarray:
        """The action chunks (B, horizon, ...) of windows `idx`, without their observations."""
        return self._lowdim[self.action_key][self.frame_indices(idx)]

    def window(self, i: int) -> dict[str, np.ndarray]:
        """One window, read the way DP's `sample_sequence` does: slice the real frames, then
        repeat the edge frames. Slower than `batch`, and independent of it."""
        self._check(np.asarray([i]))
        buffer_start, buffer_end, sample_start, sample_end = (int(v) for v in self.indices[i])
        out = {}
        for key in self.obs_keys:
            # only the first n_obs_steps frames of an observation are ever used (DP key_first_k)
            n_real = min(max(self.n_obs_steps - sample_start, 0), buffer_end - buffer_start)
            real = self._slice(key, buffer_start, buffer_start + n_real)
            out[key] = _pad(real, sample_start, sample_start + n_real,
                            self.horizon)[:self.n_obs_steps]
        real = action_vectors(self._slice(self.action_key, buffer_start, buffer_end))
        out[self.action_key] = _pad(real, sample_start, sample_end, self.horizon)
        return out

    __getitem__ = window

    def _slice(self, key: str, start: int, stop: int) -> np.ndarray:
        if key in self._images:
            return self._images[key].get(np.arange(start, stop))
        return self._lowdim[key][start:stop]

    def _check(self, idx: np.ndarray) -> np.ndarray:
        idx = np.asarray(idx, dtype=np.int64).reshape(-1)
        if len(idx) and (idx.min() < -len(self) or idx.max() >= len(self)):
            raise IndexError(f"window index out of range for {len(self)} windows")
        return idx % len(self) if len(idx) else idx


def _pad(real: np.ndarray, sample_start: int, sample_end: int, length: int) -> np.ndarray:
    """Place `real` at [sample_start, sample_end) of a `length`-frame sequence, repeating its
    first frame before and its last frame after."""
    if sample_start == 0 and sample_end == length:
        return real
    out = np.empty((length,) + real.shape[1:], real.dtype)
    out[:sample_start] = real[0]
    out[sample_start:sample_end] = real
    out[sample_end:] = real[-1]
    return out


def to_torch(batch: dict[str, np.ndarray], device: str | torch.device = "cpu",
             image_keys: Collection[str] | None = None) -> dict[str, torch.Tensor]:
    """Tensors for a model: low-dim keys float32; image keys (B, T, H, W, C) uint8 become
    (B, T, C, H, W) float in [0, 1]. `image_keys` defaults to the 5-d uint8 arrays.

    Images cross to the device as uint8 and are converted there: a quarter of the bytes.
    On the CPU a float32 array is shared with the tensor, not copied.
    """
    if image_keys is None:
        image_keys = [k for k, v in batch.items() if v.dtype == np.uint8 and v.ndim == 5]
    out = {}
    for key, value in batch.items():
        t = torch.from_numpy(np.ascontiguousarray(value)).to(device, non_blocking=True)
        out[key] = image_to_float(t) if key in image_keys else t.float()
    return out


def image_to_float(frames: torch.Tensor) -> torch.Tensor:
    """uint8 HWC frames (..., H, W, C) -> float CHW (..., C, H, W) in [0, 1]: the one place the
    image layout and scale are converted (the sampler, the policy's processor and the export)."""
    return frames.movedim(-1, -3).float().div_(255.0)


class WindowSubset:
    """Some windows of a sampler, addressed 0..n-1 like a sampler of their own: the two sides
    of a window-level split of a store too small for an episode-level one."""

    def __init__(self, sampler: "SequenceSampler", windows: np.ndarray, split: str):
        self.sampler, self.windows, self.split = sampler, np.asarray(windows, dtype=np.int64), split

    def __len__(self) -> int:
        return len(self.windows)

    # every method that takes window indices maps them; the rest is the sampler's own
    def batch(self, idx) -> dict[str, np.ndarray]:
        return self.sampler.batch(self.windows[np.asarray(idx)])

    def actions(self, idx) -> np.ndarray:
        return self.sampler.actions(self.windows[np.asarray(idx)])

    def frame_indices(self, idx) -> np.ndarray:
        return self.sampler.frame_indices(self.windows[np.asarray(idx)])

    def window_index(self, i: int):
        return self.sampler.window_index(int(self.windows[i]))

    def window(self, i: int) -> dict[str, np.ndarray]:
        return self.sampler.window(int(self.windows[i]))

    def __getattr__(self, name: str):
        return getattr(self.sampler, name)


def window_split(n_windows: int, horizon: int, val_ratio: float = 0.1
                 ) -> tuple[np.ndarray, np.ndarray]:
    """(train, valid) window indices of one episode: the last `val_ratio` of the windows (at
    least one) are held out, and the horizon - 1 windows before them are dropped from training
    so that no training window shares a frame with a validation window."""
    n_val = min(n_windows - 1, max(1, int(round(n_windows * val_ratio))))
    start = n_windows - n_val
    return np.arange(0, max(0, start - (horizon - 1))), np.arange(start, n_windows)
