"""Import an existing Diffusion Policy ReplayBuffer store (a directory or a ``.zarr.zip``).

The layout: ``data/<key>`` arrays hold every episode concatenated along time and
``meta/episode_ends`` holds each episode's exclusive end index. Episodes are cut out of blocks
of whole source chunks, so every chunk is decompressed exactly once and memory stays at about
one block per key (Push-T's images are 2.8 GB decoded). The next block of each key is read in a
worker thread while the caller works on the current one.

Images (a frame of shape H x W x C with C in 1, 3, 4 and H, W >= 16) stored as floats, as
Push-T does with values 0..255, become uint8 when every value is a whole number in 0..255, and
are an error otherwise. Everything else keeps its dtype.
"""

from __future__ import annotations

import zipfile
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from contextlib import ExitStack, closing, contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, TypeVar

import numpy as np
import zarr
import zarr.errors
import zarr.storage
from numcodecs.errors import UnknownCodecError

from sefa_data.episode import Episode, Recording
from sefa_data.errors import SefaInputError
from sefa_data.stats import first_nonfinite
from sefa_data.store.integrity import metadata_documents, unsafe_codec, unsafe_metadata

LAYOUT = "diffusion_policy_replay_buffer"
# Decoded bytes per read: enough chunks for zarr to decode in parallel, little enough to hold
# one block per key (plus the one being read ahead) in memory.
_BLOCK_BYTES = 128 << 20
# Bytes per step of the uint8 conversion: small enough to stay in the CPU cache between the cast
# and the check, which halves its cost against whole-block numpy passes.
_TILE_BYTES = 1 << 20

T = TypeVar("T")


@dataclass(frozen=True)
class _KeySpec:
    source: str  # the array name under data/
    key: str  # the dataset key it is yielded under
    to_uint8: bool  # a float image to convert
    check_finite: bool  # float values that must not be NaN or Inf


def read_dp_zarr(path: str | Path, renames: dict[str, str] | None = None,
                 keys: list[str] | None = None) -> Recording:
    """Open a ReplayBuffer store read-only; episodes are read lazily, in order.

    `keys` picks source arrays (default: all under data/); `renames` maps a source array name to
    the dataset key it is yielded under (e.g. ``{"img": "observation.images.top"}``). Problems
    with the store's structure raise here; bad values raise from the episode iterator.
    """
    file = str(path)
    renames = dict(renames or {})
    _register_image_codecs()
    with _open_root(file) as root:
        arrays = _data_arrays(root, file)
        ends = _episode_ends(root, file)
        names = _key_names(sorted(arrays), keys, renames, file)
        _check_lengths(arrays, ends, file)
        specs = [_spec(source, key, arrays[source]) for source, key in names.items()]
        meta = _meta(root, arrays, names, specs, ends, file)
    return Recording(meta=meta, episodes=_episodes(file, specs, ends))


# ----------------------------------------------------------------------------- store structure

@contextmanager
def _open_root(file: str) -> Iterator[zarr.Group]:
    path = Path(file)
    if not path.exists():
        raise SefaInputError("file not found", file=file)
    if path.is_file():
        if not zipfile.is_zipfile(path):
            raise SefaInputError("not a Zarr store (a file, but not a .zarr.zip)", file=file)
        with zipfile.ZipFile(path) as z:
            names = [n for n in z.namelist() if n.rsplit("/", 1)[-1] in
                     (".zarray", "zarr.json", ".zmetadata")]
            unsafe = unsafe_metadata((n, z.read(n)) for n in names)
    else:
        unsafe = unsafe_metadata(metadata_documents(path))
    if unsafe is not None:
        raise SefaInputError(f"uses {unsafe[1]}; sefa never decodes it, since unpickling data "
                             "from a file can run arbitrary code", file=file, key=unsafe[0])
    if path.is_file():
        store = zarr.storage.ZipStore(path, mode="r")
    else:
        store = zarr.storage.LocalStore(path, read_only=True)
    try:
        try:
            root = zarr.open_group(store, mode="r")
        except (zarr.errors.GroupNotFoundError, FileNotFoundError, ValueError) as e:
            raise SefaInputError(f"not a Zarr store ({e})", file=file) from None
        yield root
    finally:
        store.close()


def _data_arrays(root: zarr.Group, file: str) -> dict[str, zarr.Array]:
    data = _member(root, "data", zarr.Group, file)
    try:
        members = dict(sorted(data.members()))
    except UnknownCodecError as e:
        raise SefaInputError(f"{e} (Diffusion Policy's Jpeg2k image codec comes with "
                             "`pip install imagecodecs`)", file=file, key="data") from None
    nested = sorted(name for name, node in members.items() if not isinstance(node, zarr.Array))
    if nested:
        raise SefaInputError("a group inside data/ (a ReplayBuffer holds only arrays)",
                             file=file, key=f"data/{nested[0]}")
    if not members:
        raise SefaInputError("no arrays under data/", file=file, key="data")
    for name, arr in members.items():
        _check_safe_numeric(arr, file, f"data/{name}")
    return members


def _check_safe_numeric(arr: zarr.Array, file: str, key: str) -> None:
    """Refuse, before any chunk is read, codecs that would unpickle (run code from the file)
    and arrays that are not numbers."""
    codec = unsafe_codec(arr)
    if codec is not None:
        raise SefaInputError(f"uses {codec}; sefa never decodes it, since unpickling data "
                             "from a file can run arbitrary code", file=file, key=key)
    if arr.dtype.kind not in "biuf":
        raise SefaInputError(f"{arr.dtype} values: sefa imports numbers (bool, int, uint, "
                             "float) only", file=file, key=key)


def _register_image_codecs() -> None:
    """Diffusion Policy stores images with imagecodecs' Jpeg2k codec, registered with numcodecs
    by the reader; do the same when imagecodecs is installed."""
    try:
        from imagecodecs.numcodecs import register_codecs
    except ImportError:
        return
    register_codecs()


def _member(group: zarr.Group, name: str, kind: type, file: str) -> zarr.Group | zarr.Array:
    try:
        member = group[name]
    except KeyError:
        member = None
    if not isinstance(member, kind):
        raise SefaInputError("missing (not a Diffusion Policy ReplayBuffer store)",
                             file=file, key=name if group.path == "" else f"{group.path}/{name}")
    return member


def _episode_ends(root: zarr.Group, file: str) -> np.ndarray:
    """meta/episode_ends as int64, checked: integers, strictly increasing, no empty episode."""
    key = "meta/episode_ends"
    arr = _member(_member(root, "meta", zarr.Group, file), "episode_ends", zarr.Array, file)
    codec = unsafe_codec(arr)
    if codec is not None:
        raise SefaInputError(f"uses {codec}; sefa never decodes it, since unpickling data "
                             "from a file can run arbitrary code", file=file, key=key)
    ends = arr[:]
    if ends.dtype.kind not in "iu" or ends.ndim != 1:
        raise SefaInputError(f"must be a 1-D integer array, got {ends.dtype} {ends.shape}",
                             file=file, key=key)
    ends = ends.astype(np.int64)
    lengths = np.diff(ends, prepend=0)
    if (lengths <= 0).any():
        i = int(np.argmax(lengths <= 0))
        before = int(ends[i - 1]) if i else 0
        raise SefaInputError(f"not strictly increasing ({before} then {int(ends[i])})",
                             file=file, key=key, where=f"index {i}")
    return ends


def _key_names(sources: list[str], keys: list[str] | None, renames: dict[str, str],
               file: str) -> dict[str, str]:
    """Source array name -> dataset key, for the arrays to read."""
    listing = ", ".join(sources)
    if keys is not None and not keys:
        raise SefaInputError(f"keys is empty; pick some of: {listing}", file=file)
    for name in list(keys or []) + list(renames):
        if name not in sources:
            raise SefaInputError(f"no array '{name}' under data/; it has: {listing}", file=file)
    picked = [s for s in sources if keys is None or s in keys]
    names = {s: renames.get(s, s) for s in picked}
    targets = list(names.values())
    clash = next((k for k in targets if targets.count(k) > 1), None)
    if clash is not None:
        raise SefaInputError(f"two arrays would both be named '{clash}' after renaming",
                             file=file)
    return names


def _check_lengths(arrays: dict[str, zarr.Array], ends: np.ndarray, file: str) -> None:
    steps = int(ends[-1]) if len(ends) else 0
    for name, arr in arrays.items():
        if arr.ndim == 0 or arr.shape[0] != steps:
            length = arr.shape[0] if arr.ndim else "a scalar"
            raise SefaInputError(f"has {length} steps but meta/episode_ends ends at {steps}",
                                 file=file, key=f"data/{name}")


def _is_image(frame_shape: tuple[int, ...]) -> bool:
    return len(frame_shape) == 3 and frame_shape[2] in (1, 3, 4) and min(frame_shape[:2]) >= 16


def _spec(source: str, key: str, arr: zarr.Array) -> _KeySpec:
    is_float = arr.dtype.kind == "f"
    image = _is_image(tuple(arr.shape[1:]))
    return _KeySpec(source, key, to_uint8=image and is_float, check_finite=is_float and not image)


def _meta(root: zarr.Group, arrays: dict[str, zarr.Array], names: dict[str, str],
          specs: list[_KeySpec], ends: np.ndarray, file: str) -> dict:
    converted = {s.source for s in specs if s.to_uint8}
    attrs = dict(root.attrs)
    # a Diffusion Policy store does not record its rate; a store written by sefa does
    fps = {"fps": float(attrs["fps"])} if isinstance(attrs.get("fps"), (int, float)) else {}
    return {
        **fps,
        "format": "zarr",
        "layout": LAYOUT,
        "zarr_format": root.metadata.zarr_format,
        "store": "zip" if Path(file).is_file() else "directory",
        "n_episodes": len(ends),
        "steps": int(ends[-1]) if len(ends) else 0,
        "attrs": attrs,
        "keys": {name: {"key": names.get(name),  # None: present but not read
                        "dtype": str(arr.dtype),
                        "dtype_out": "uint8" if name in converted else str(arr.dtype),
                        "shape": list(arr.shape),
                        "chunks": list(arr.chunks),
                        "compressors": [_codec_config(c) for c in arr.compressors]}
                 for name, arr in sorted(arrays.items())},
    }


def _codec_config(codec: object) -> object:
    for method in ("get_config", "to_dict"):  # numcodecs codecs (format 2), zarr 3 codecs
        if hasattr(codec, method):
            return getattr(codec, method)()
    return repr(codec)


# ----------------------------------------------------------------------------- episodes

def _episodes(file: str, specs: list[_KeySpec], ends: np.ndarray) -> Iterator[Episode]:
    lengths = np.diff(ends, prepend=0)
    with _open_root(file) as root, ExitStack() as readers:
        columns = []
        for spec in specs:
            blocks = _read_ahead(_blocks(root["data"][spec.source], spec, file))
            # closed before the store, so no read is still in flight when the store closes
            readers.enter_context(closing(blocks))
            columns.append(_split(blocks, lengths))
        for index, pieces in enumerate(zip(*columns)):
            data = {spec.key: piece for spec, piece in zip(specs, pieces)}
            yield Episode(data=data, source=file, label=f"episode_{index}")


def _blocks(arr: zarr.Array, spec: _KeySpec, file: str) -> Iterator[np.ndarray]:
    """The array from start to end in blocks of whole chunks (shards, when it has them)."""
    step = _block_rows(arr)
    for start in range(0, arr.shape[0], step):
        block = arr[start:start + step]
        if spec.to_uint8:
            block = _to_uint8(block, file, f"data/{spec.source}", start)
        elif spec.check_finite:
            _check_finite(block, file, f"data/{spec.source}", start)
        yield block


def _block_rows(arr: zarr.Array) -> int:
    chunk_rows = (arr.shards or arr.chunks)[0]
    chunk_bytes = chunk_rows * max(1, int(np.prod(arr.shape[1:])) * arr.dtype.itemsize)
    return chunk_rows * max(1, _BLOCK_BYTES // chunk_bytes)


def _to_uint8(block: np.ndarray, file: str, key: str, start: int) -> np.ndarray:
    """Float image values that are whole numbers in 0..255, as uint8."""
    out = np.empty(block.shape, np.uint8)
    frame_bytes = max(1, block[:1].nbytes)
    tile = max(1, _TILE_BYTES // frame_bytes)
    # A cast value always lies in 0..255 and is whole, so it equals its source exactly when the
    # source was whole and in range: one compare catches fractions, out-of-range values and NaN.
    with np.errstate(invalid="ignore"):
        for s in range(0, len(block), tile):
            src, dst = block[s:s + tile], out[s:s + tile]
            np.copyto(dst, src, casting="unsafe")
            if not np.array_equal(dst, src):
                row = s + int(np.argmin((dst == src).reshape(len(src), -1).all(axis=1)))
                bad = block[row][block[row] != out[row]].flat[0]
                raise SefaInputError(f"image value {bad} is not a whole number in 0..255, so it "
                                     "cannot become uint8", file=file, key=key,
                                     where=f"frame {start + row}")
    return out


def _check_finite(block: np.ndarray, file: str, key: str, start: int) -> None:
    bad = first_nonfinite(block)
    if bad is not None:
        raise SefaInputError("NaN or Inf value", file=file, key=key, where=f"step {start + bad}")


def _read_ahead(items: Iterator[T]) -> Iterator[T]:
    """Yield `items` while a worker thread already produces the next one (zarr decoding and
    numpy release the GIL, so reading overlaps with whatever the caller does meanwhile)."""
    with ThreadPoolExecutor(max_workers=1) as pool:
        future = None  # a Ctrl-C can land inside the first submit
        try:
            future = pool.submit(next, items, None)
            while (item := future.result()) is not None:
                future = pool.submit(next, items, None)
                yield item
        finally:
            if future is not None:
                future.cancel()


def _split(blocks: Iterator[np.ndarray], lengths: np.ndarray) -> Iterator[np.ndarray]:
    """Cut consecutive blocks into consecutive pieces of `lengths` rows. A piece inside one
    block is a view of it; only a piece across a block boundary is copied."""
    pending: deque[np.ndarray] = deque()
    have = 0
    for n in lengths:
        while have < n:
            block = next(blocks)  # the lengths were checked against the arrays
            pending.append(block)
            have += len(block)
        parts, need = [], int(n)
        while need:
            head = pending.popleft()
            parts.append(head[:need])
            if len(head) > need:
                pending.appendleft(head[need:])
            need -= len(parts[-1])
        have -= int(n)
        yield parts[0] if len(parts) == 1 else np.concatenate(parts)
