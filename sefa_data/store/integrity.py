"""Integrity of an episode store: content checksums recorded at commit, and the checks at open.

The checksum list ``.sefa-checksums.json`` at the store's root records the size and SHA-256 of
every file of the store (each chunk and each metadata file; not the journal, not itself). Each
commit rehashes only what the append wrote or rewrote (new chunks, the partial last chunk of
each array, ``meta/``, metadata), so appending stays proportional to the new data; the image
chunks an append writes are hashed from the bytes in memory as they are written.

`verify_store` checks, cheapest first, and refuses a damaged store with one line naming what is
damaged:

* ``quick`` (every `EpisodeStore.open`: ingest, train, eval, inspect): the attributes are
  well-formed; every chunk of every array is in the list, and every listed file is present with
  its recorded size (a deleted or truncated chunk; zarr would read a missing chunk as zeros);
  ``meta/episode_ends`` agrees with every array's length and with the per-episode arrays; no
  array uses the pickle codec; and the checksums of everything except the image chunks
  (metadata, ``meta/``, low-dimensional arrays: a few MB even for large stores).
* ``full`` (``sefa inspect --verify``): the checksums of the image chunks too.

Stores written before checksums existed have no list: they get the attribute and episode checks
only, and their next append writes a list of the files as they are then.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import math
import os
from pathlib import Path
from typing import Any, Iterable, Literal

import numpy as np
import zarr

from sefa_data.errors import SefaInputError
from sefa_data import atomic
from sefa_data.store.journal import is_journal_path

MANIFEST = ".sefa-checksums.json"
ALGORITHM = "sha256"
Level = Literal["none", "quick", "full"]
_DAMAGED = "the store is damaged; re-ingest its sources into a new store"


def damaged(what: str, store: Path | str, key: str | None = None) -> SefaInputError:
    return SefaInputError(f"{what}: {_DAMAGED}", file=str(store), key=key)


def digest(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def hash_file(path: Path) -> tuple[int, str]:
    h = hashlib.sha256()
    size = 0
    with open(path, "rb") as f:
        while block := f.read(1 << 22):
            h.update(block)
            size += len(block)
    return size, h.hexdigest()


def is_content(rel: str) -> bool:
    """Files the checksum list covers: everything but the journal and the list itself."""
    return not is_journal_path(rel) and not rel.startswith(MANIFEST)


def store_files(root: Path) -> set[str]:
    """Relative paths of the store's content files (os.walk and strings: a store holds a file
    per image frame, and pathlib objects for each cost more than the walk)."""
    out = set()
    base = len(str(root)) + 1
    for folder, dirs, files in os.walk(root):
        if folder == str(root):
            dirs[:] = [d for d in dirs if is_content(d)]
            files = [f for f in files if is_content(f)]
        prefix = folder[base:] + "/" if len(folder) > base else ""
        out.update(prefix + f for f in files)
    return out


def load_manifest(root: Path) -> dict[str, list] | None:
    """The recorded {path: [size, sha256]}, or None for a store written without checksums."""
    path = root / MANIFEST
    if not path.exists():
        return None
    try:
        data = json.loads(path.read_text())
        files = data["files"]
        if data.get("algorithm") != ALGORITHM or not isinstance(files, dict):
            raise ValueError(f"unknown layout (algorithm {data.get('algorithm')!r})")
        for rel, entry in files.items():
            if not (isinstance(entry, list) and len(entry) == 2 and isinstance(entry[0], int)
                    and isinstance(entry[1], str)):
                raise ValueError(f"bad entry for {rel}")
    except (ValueError, KeyError, TypeError, AttributeError) as e:
        raise damaged(f"the checksum list is unreadable ({e})", root, MANIFEST) from None
    return files


def write_manifest(root: Path, before: set[str] | None, rewritten: Iterable[str],
                   known: dict[str, tuple[int, str]]) -> None:
    """Record the store's files after an append: entries of untouched files are kept, the rest
    hashed (`known` holds digests computed while writing). `before` is the file list at the
    start of the append; None (or no earlier list) rehashes everything."""
    old = load_manifest(root) if before is not None else None
    current = store_files(root)
    if old is None:
        changed = current
    else:
        changed = (current - before) | (set(rewritten) & current) | (current - set(old))
    files = {rel: old[rel] for rel in current - changed} if old is not None else {}
    for rel in changed:
        files[rel] = list(known[rel]) if rel in known else list(hash_file(root / rel))
    atomic.write_text(root / MANIFEST, json.dumps(
        {"algorithm": ALGORITHM, "files": dict(sorted(files.items()))}, separators=(",", ":")))


# --------------------------------------------------------------------------- verification

def unsafe_codec(arr: zarr.Array) -> str | None:
    """The name of a codec that would unpickle on read (arbitrary code), or None."""
    text = json.dumps(arr.metadata.to_dict(), default=str).lower()
    if "pickle" in text:
        return "pickle"
    if arr.dtype == object:
        return "an object dtype (decoded by a Python object codec)"
    return None


def _codec_ids(node: Any) -> Iterable[str]:
    """Every codec id or name in a metadata document (v2 compressor/filters, v3 codecs)."""
    if isinstance(node, dict):
        for k, v in node.items():
            if k in ("id", "name", "object_codec_id") and isinstance(v, str):
                yield v.lower()
            yield from _codec_ids(v)
    elif isinstance(node, list):
        for v in node:
            yield from _codec_ids(v)


def unsafe_metadata(documents: Iterable[tuple[str, bytes]]) -> tuple[str, str] | None:
    """(metadata file, reason) for the first array whose metadata asks for unpickling or for
    Python objects, read from the raw JSON before zarr builds any codec; None when all are safe.
    `documents` are (path, bytes) of .zarray / zarr.json / .zmetadata files."""
    for name, raw in documents:
        try:
            doc = json.loads(raw)
        except ValueError:
            continue  # zarr reports broken metadata itself
        if any("pickle" in c for c in _codec_ids(doc)):
            return name, "the pickle codec"
        text = json.dumps(doc)
        if '"|O"' in text or '"object"' in text:
            return name, "an object dtype (decoded by a Python object codec)"
    return None


def metadata_documents(root: Path) -> Iterable[tuple[str, bytes]]:
    """(relative path, bytes) of the array metadata files under `root` (os.walk: a store has a
    file per image frame, and pathlib's per-file objects would cost more than the reads)."""
    for folder, dirs, files in os.walk(root):
        dirs[:] = sorted(d for d in dirs if not d.startswith(".sefa-journal"))
        for name in sorted(set(files) & {".zarray", "zarr.json", ".zmetadata"}):
            path = os.path.join(folder, name)
            with open(path, "rb") as f:
                yield os.path.relpath(path, root), f.read()


def chunk_paths(arr: zarr.Array) -> Iterable[str]:
    grid = [range(math.ceil(s / c)) if s else range(0) for s, c in zip(arr.shape, arr.chunks)]
    encode = arr.async_array.metadata.encode_chunk_key
    for coords in itertools.product(*grid):
        yield f"{arr.path}/{encode(coords)}"


def check_attrs(attrs: dict, store: Path, format_version: int) -> None:
    """The attributes sefa relies on, with the types it relies on."""
    def bad(key: str, what: str) -> SefaInputError:
        return damaged(f"broken store attributes: {what}", store, key)

    fmt = attrs.get("sefa_format")
    if not isinstance(fmt, int) or isinstance(fmt, bool) or not 1 <= fmt <= format_version:
        raise bad("sefa_format", f"{fmt!r} is not a store format this sefa reads "
                                 f"(1..{format_version})")
    fps = attrs.get("fps")
    if not isinstance(fps, (int, float)) or isinstance(fps, bool) or not math.isfinite(fps) \
            or fps <= 0:
        raise bad("fps", f"{fps!r} is not a positive frame rate")
    features = attrs.get("features")
    if not isinstance(features, dict):
        raise bad("features", "missing or not a mapping")
    for key, f in features.items():
        if not (isinstance(f, dict) and isinstance(f.get("dtype"), str)
                and isinstance(f.get("shape"), list)
                and all(isinstance(d, int) and d > 0 for d in f["shape"])
                and f.get("type") in ("image", "low_dim")):
            raise bad(f"features.{key}", "needs dtype, shape and type (image or low_dim)")
        try:
            np.dtype(f["dtype"])
        except TypeError:
            raise bad(f"features.{key}", f"unknown dtype {f['dtype']!r}") from None
    for name in ("stats", "image_histograms"):
        if not isinstance(attrs.get(name), dict):
            raise bad(name, "missing or not a mapping")
    sources = attrs.get("sources")
    if not isinstance(sources, list) or not all(
            isinstance(s, dict) and isinstance(s.get("path"), str)
            and isinstance(s.get("sha256"), str) and isinstance(s.get("episodes"), list)
            and len(s["episodes"]) == 2 for s in sources):
        raise bad("sources", "not a list of {path, sha256, episodes: [first, count]}")
    split = attrs.get("split")
    if not (isinstance(split, dict) and isinstance(split.get("val_ratio"), (int, float))
            and 0 <= split["val_ratio"] < 1 and isinstance(split.get("seed"), int)):
        raise bad("split", "needs val_ratio in [0, 1) and an integer seed")


def broken_metadata(path: Path) -> str | None:
    """The first metadata file under `path` that is not valid JSON, for the error line."""
    for p in sorted(path.rglob("*")):
        rel = str(p.relative_to(path))
        if _is_metadata(rel) and is_content(rel):
            try:
                json.loads(p.read_bytes())
            except (ValueError, UnicodeDecodeError, OSError):
                return rel
    return None


def _arrays(group: zarr.Group, store: Path) -> dict[str, zarr.Array]:
    try:
        return {arr.path: arr for _, arr in group.arrays()}
    except Exception as e:  # a broken .zarray / zarr.json
        bad = broken_metadata(store / group.path)
        if bad is not None:
            raise damaged("not valid JSON", store, f"{group.path}/{bad}") from None
        raise damaged(f"unreadable array metadata ({type(e).__name__}: {e})", store,
                      group.path) from None


def _group(root: zarr.Group, name: str, store: Path) -> zarr.Group:
    try:
        node = root[name]
    except KeyError:
        node = None
    except Exception as e:
        raise damaged(f"unreadable group metadata ({type(e).__name__}: {e})", store, name) from None
    if not isinstance(node, zarr.Group):
        raise damaged("missing group", store, name)
    return node


def mask_group(root: zarr.Group) -> zarr.Group:
    """The per-episode masks: mask/ at the root, or meta/mask in stores written before the
    masks moved out of meta/ (where Diffusion Policy's 2023 loader trips on a group)."""
    return root["mask"] if "mask" in root else root["meta"]["mask"]


def verify_store(path: Path, root: zarr.Group, attrs: dict, format_version: int,
                 level: Level = "quick") -> dict[str, Any]:
    """Check the store (see the module docstring); returns counts for `sefa inspect --verify`."""
    if level == "none":
        return {}
    check_attrs(attrs, path, format_version)
    features = attrs["features"]
    data, meta = _group(root, "data", path), _group(root, "meta", path)
    mask = _group(root, "mask", path) if "mask" in root else _group(meta, "mask", path)
    arrays = {**_arrays(data, path), **_arrays(meta, path), **_arrays(mask, path)}
    for name, arr in arrays.items():
        codec = unsafe_codec(arr)
        if codec is not None:
            raise damaged(f"uses {codec}, which sefa never decodes (it can run code)", path, name)
    manifest = load_manifest(path)
    if manifest is not None:
        _check_presence(path, arrays, manifest)
    _check_episodes(path, arrays, features, attrs["sources"])
    hashed = 0
    if manifest is not None:
        images = tuple(f"data/{k}/" for k, f in features.items() if f["type"] == "image")
        for rel, (size, hexdigest) in manifest.items():
            if level != "full" and images and rel.startswith(images) and not _is_metadata(rel):
                continue
            if hash_file(path / rel)[1] != hexdigest:
                key, _, name = rel.rpartition("/")
                raise damaged(f"{'chunk ' if not _is_metadata(rel) else ''}{name} does not "
                              "match its checksum", path, key or None)
            hashed += 1
    return {"checksums": manifest is not None, "files": len(manifest or {}),
            "files_hashed": hashed, "level": level}


_METADATA_NAMES = frozenset((".zarray", ".zattrs", ".zgroup", ".zmetadata", "zarr.json"))


def _is_metadata(rel: str) -> bool:
    return rel.rpartition("/")[2] in _METADATA_NAMES


def _check_presence(path: Path, arrays: dict[str, zarr.Array], manifest: dict) -> None:
    root = str(path) + os.sep  # plain strings: pathlib costs more than the stat per file
    stat = os.stat
    for rel, (size, _) in manifest.items():
        try:
            actual = stat(root + rel).st_size
        except FileNotFoundError:
            actual = None
        if actual != size:
            key, _, name = rel.rpartition("/")
            what = "chunk " + name if not _is_metadata(rel) else name
            if actual is None:
                zeros = " (zarr would read it as zeros)" if not _is_metadata(rel) else ""
                raise damaged(f"{what} is missing{zeros}", path, key or None)
            raise damaged(f"{what} is {actual} bytes where {size} were written"
                          + (" (truncated?)" if actual < size else ""), path, key or None)
    for name, arr in arrays.items():  # what the arrays' metadata says must be there
        for rel in chunk_paths(arr):
            if rel not in manifest:
                raise damaged(f"chunk {rel[len(name) + 1:]} is not in the checksum list", path,
                              name)


def _check_episodes(path: Path, arrays: dict[str, zarr.Array], features: dict,
                    sources: list[dict]) -> None:
    data = {n[len("data/"):]: a for n, a in arrays.items() if n.startswith("data/")}
    if set(data) != set(features):
        extra = sorted(set(data) ^ set(features))[0]
        where = "no feature entry" if extra in data else "no array under data/"
        raise damaged(f"{where} for this key", path, f"data/{extra}")
    for key, arr in data.items():
        f = features[key]
        if str(arr.dtype) != f["dtype"] or list(arr.shape[1:]) != f["shape"]:
            raise damaged(f"array is {arr.dtype} {tuple(arr.shape[1:])} where the attributes "
                          f"say {f['dtype']} {tuple(f['shape'])}", path, f"data/{key}")
    ends_arr = arrays.get("meta/episode_ends")
    if ends_arr is None:
        raise damaged("missing", path, "meta/episode_ends")
    ends = ends_arr[:]
    if ends.ndim != 1 or ends.dtype.kind not in "iu" or len(ends) == 0:
        raise damaged(f"not a non-empty 1-D integer array ({ends.dtype} {ends.shape})", path,
                      "meta/episode_ends")
    lengths = np.diff(ends, prepend=0)
    if (lengths <= 0).any():
        i = int(np.argmax(lengths <= 0))
        raise damaged(f"episode {i} has {int(lengths[i])} frames (ends must increase)", path,
                      "meta/episode_ends")
    for key, arr in data.items():
        if arr.shape[0] != ends[-1]:
            raise damaged(f"{arr.shape[0]} frames where meta/episode_ends ends at {ends[-1]}",
                          path, f"data/{key}")
    for name, arr in arrays.items():
        per_episode = name.startswith(("meta/", "mask/")) and name != "meta/episode_ends"
        if per_episode and arr.shape != ends.shape:
            raise damaged(f"{arr.shape[0] if arr.ndim else 'scalar'} entries for {len(ends)} "
                          "episodes", path, name)
    if "meta/episode_source" in arrays:
        src = arrays["meta/episode_source"][:]
        if len(src) and (src.min() < 0 or src.max() >= len(sources)):
            raise damaged(f"names source {int(src.max())} of {len(sources)}", path,
                          "meta/episode_source")
    counted = sum(int(s["episodes"][1]) for s in sources)
    if counted != len(ends):
        raise damaged(f"the sources account for {counted} episodes, meta/episode_ends has "
                      f"{len(ends)}", path, "sources")
