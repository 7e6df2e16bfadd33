"""Couplings and aligned couplings: the artifacts between reflow, alignment and distillation.
This module alone writes, reads and validates them.

    couplings.zarr (reflow)          aligned.zarr (align)
    noise   (M, T, Da) float32       noise    (M, T, Da) float32   x0, unchanged
    action  (M, T, Da) float32       target   (M, T, Da) float32   x1: expert or generated chunk
    window  (M,) int64               window   (M,) int64           row of the train sampler
                                     replaced (M,) bool, distance (M,) float32

Both carry their provenance in their attributes: `normalizer_sha256`, the normalizer whose
space the chunks are in (`Normalizer.digest`), and `window_spec`, what a window index means
(horizon, observation steps, keys, the number of training windows). A reader that trains on
them (`read_pairs`) checks both against the policy it trains, so couplings made under another
normalizer or window definition are an error, not a silent mismatch. Artifacts written before
these attributes existed are read without that check.
"""

from __future__ import annotations

import shutil
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Iterator, Literal

import numpy as np
import zarr

from sefa_data import atomic
from sefa_data.errors import NonFiniteError, SefaInputError

COUPLING_KEYS = ("noise", "action", "window")
ALIGNED_KEYS = ("noise", "target", "window")
PROVENANCE_KEYS = ("normalizer_sha256", "window_spec")
ALIGNED_VARIANTS = ("same_window", "matching_obs")


# The distance between a generated chunk and its window's expert chunk: what aligned.zarr's
# `distance` holds and its `metric` attribute names. Reflow reports it (the expert drift) and
# alignment selects by it, so it lives here, with the artifacts both stages write.
METRIC = ("mean over the horizon of the per-step L2 norm between generated and expert chunk, "
          "in normalized action space")


def chunk_distance(generated: np.ndarray, expert: np.ndarray) -> np.ndarray:
    """(M, T, Da), (M, T, Da) -> (M,) float32: mean over T of the L2 norm over Da.

    Accumulated in float64 so that the eps comparison does not depend on summation order.
    """
    g = np.asarray(generated, np.float64)
    e = np.asarray(expert, np.float64)
    if g.shape != e.shape or g.ndim != 3:
        raise ValueError(f"need two (M, T, Da) arrays of one shape, got {g.shape} and {e.shape}")
    return np.linalg.norm(g - e, axis=-1).mean(axis=-1).astype(np.float32)


@dataclass(frozen=True)
class PairSource:
    """What a reflowed flow or a student trains on: `couplings` (the generated chunks as
    targets) or `aligned` (the aligned targets), and the kind of policy that results."""

    path: Path
    target: Literal["action", "target"]
    kind: Literal["reflow", "sefa_one_step", "reflow_one_step"]

    @classmethod
    def couplings(cls, path: str | Path, kind: str) -> "PairSource":
        return cls(Path(path), "action", kind)

    @classmethod
    def aligned(cls, path: str | Path, kind: str) -> "PairSource":
        return cls(Path(path), "target", kind)


@dataclass
class Couplings:
    noise: np.ndarray  # (M, T, Da) float32
    action: np.ndarray  # (M, T, Da) float32, normalized: the generated chunk, or the aligned target
    window: np.ndarray  # (M,) int64
    attrs: dict[str, Any]


def provenance(normalizer_sha256: str, cfg, n_train_windows: int) -> dict[str, Any]:
    """The attributes that tie couplings to the space and windows they were made in."""
    p, meta = cfg.policy, cfg.shape_meta
    return {"normalizer_sha256": normalizer_sha256,
            "window_spec": {"horizon": p.horizon, "n_obs_steps": p.n_obs_steps,
                            "n_action_steps": p.n_action_steps, "action_key": meta.action.key,
                            "obs": {k: asdict(s) for k, s in meta.obs.items()},
                            "n_train_windows": int(n_train_windows)}}


def check_provenance(attrs: dict[str, Any], expected: dict[str, Any], file: str) -> None:
    """Couplings read for training must come from the same normalizer and window definition."""
    if attrs.get("normalizer_sha256") not in (None, expected["normalizer_sha256"]):
        raise SefaInputError("the couplings were made under another normalizer than the policy "
                             "trained on them (regenerate them from this policy: sefa reflow "
                             "--force)", file=file, key="normalizer_sha256")
    spec = attrs.get("window_spec")
    if spec is not None and spec != expected["window_spec"]:
        differ = sorted(k for k in set(spec) | set(expected["window_spec"])
                        if spec.get(k) != expected["window_spec"].get(k))
        raise SefaInputError(f"the couplings' windows are not this policy's ({', '.join(differ)} "
                             f"differ)", file=file, key="window_spec")


# --------------------------------------------------------------------------- reading


def read_couplings(path: str | Path, *, target: str = "action",
                   expect: dict[str, Any] | None = None) -> Couplings:
    """The group at `path` (couplings, or aligned couplings with target="target"), checked for
    keys, shapes, finite values and, given `expect` (see `provenance`), where it was made."""
    path = Path(path)
    file = str(path)
    if not path.exists():
        raise SefaInputError("no such couplings artifact (run the reflow stage first)", file=file)
    try:
        root = zarr.open_group(file, mode="r")
    except Exception as e:  # zarr raises several types for a directory that is not a group
        raise SefaInputError(f"not a Zarr group ({type(e).__name__})", file=file) from None
    keys = ("noise", target, "window")
    arrays = {}
    for key in keys:
        if key not in root.array_keys():
            raise SefaInputError(f"no array (couplings need {', '.join(keys)})", file=file, key=key)
        arrays[key] = root[key][:]
    noise, action, window = arrays["noise"], arrays[target], arrays["window"]
    _check_arrays(noise, action, window, file, target)
    attrs = dict(root.attrs)
    if expect is not None:
        check_provenance(attrs, expect, file)
    return Couplings(noise.astype(np.float32), action.astype(np.float32),
                     window.astype(np.int64), attrs)


def _check_arrays(noise: np.ndarray, action: np.ndarray, window: np.ndarray, file: str,
                  target: str) -> None:
    for key, a in (("noise", noise), (target, action)):
        if a.ndim != 3 or not np.issubdtype(a.dtype, np.floating):
            raise SefaInputError(f"need a float (M, T, Da) array, got {a.dtype} {a.shape}",
                                 file=file, key=key)
        if not np.isfinite(a).all():
            bad = int(np.flatnonzero(~np.isfinite(a).reshape(len(a), -1).all(axis=1))[0])
            raise SefaInputError("NaN or Inf", file=file, key=key, where=f"coupling {bad}")
    if noise.shape != action.shape:
        raise SefaInputError(f"shape {action.shape} differs from noise {noise.shape}",
                             file=file, key=target)
    if window.shape != (len(action),) or not np.issubdtype(window.dtype, np.integer):
        raise SefaInputError(f"need an integer ({len(action)},) array, got {window.dtype} "
                             f"{window.shape}", file=file, key="window")
    if len(action) == 0:
        raise SefaInputError("no couplings (M = 0)", file=file, key=target)


def aligned_attrs(path: str | Path) -> dict[str, Any]:
    """The attributes of an aligned artifact: eps, how it was chosen, n, n_replaced, ..."""
    if not _is_aligned_artifact(Path(path)):
        raise SefaInputError("not an aligned artifact (run the align stage first)", file=str(path))
    return dict(zarr.open_group(str(path), mode="r").attrs)


def read_pairs(source: PairSource, expect: dict[str, Any], n_train_windows: int) -> Couplings:
    """What a reflowed flow or a student trains on, checked against the policy it trains."""
    c = read_couplings(source.path, target=source.target, expect=expect)
    if c.window.min() < 0 or c.window.max() >= n_train_windows:
        raise SefaInputError(f"couplings refer to window {int(c.window.max())} but the store has "
                             f"{n_train_windows} training windows", file=str(source.path))
    return c


# --------------------------------------------------------------------------- writing


def write_couplings(out: Path, noise: np.ndarray, action: np.ndarray, window: np.ndarray,
                    attrs: dict[str, Any]) -> None:
    """The reflow stage's couplings, written beside `out` and renamed into place; chunks
    that are not finite (a diverged flow) are refused before anything is written."""
    rows = ~np.isfinite(action).reshape(len(action), -1).all(axis=1)
    if rows.any():
        raise NonFiniteError(f"the flow's ODE solve gave NaN or Inf for {int(rows.sum())} of "
                             f"{len(action)} couplings (first: {int(np.flatnonzero(rows)[0])}); "
                             "no couplings are written (did its training diverge?)", file=str(out))
    m, horizon, action_dim = noise.shape
    chunk = (max(1, 65536 // (horizon * action_dim)), horizon, action_dim)
    with _building(out) as root:
        root.create_array("noise", shape=noise.shape, dtype="f4", chunks=chunk)[:] = noise
        root.create_array("action", shape=action.shape, dtype="f4", chunks=chunk)[:] = action
        root.create_array("window", shape=(m,), dtype="i8", chunks=(chunk[0] * 16,))[:] = window
        root.update_attributes(attrs)


def write_aligned(out_path: str | Path, arrays: dict[str, np.ndarray], attrs: dict[str, Any]
                  ) -> None:
    """The aligned couplings, written beside `out_path` and renamed into place. An existing
    `out_path` is replaced only if it is an aligned artifact itself."""
    out_path = Path(out_path)
    if out_path.exists() and not _is_aligned_artifact(out_path):
        raise SefaInputError("exists and is not an aligned artifact; not overwriting it",
                             file=str(out_path))
    out_path.parent.mkdir(parents=True, exist_ok=True)
    with _building(out_path) as root:
        for name, data in arrays.items():
            root.create_array(name, data=data, chunks=_row_chunks(data))
        root.update_attributes(attrs)


@contextmanager
def _building(out: Path) -> Iterator[zarr.Group]:
    """A Zarr format-2 group under a temporary name, renamed to `out` when the block ends;
    a failure at any point (opening the group included) removes it and leaves `out` as it was."""
    tmp = atomic.tmp_name(Path(out))
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        yield zarr.open_group(str(tmp), mode="w", zarr_format=2)
        atomic.replace_dir(tmp, Path(out))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _row_chunks(data: np.ndarray) -> tuple[int, ...]:
    """Whole rows, about 4 MB a chunk: readers take rows, never parts of one."""
    rows = max(1, min(len(data), (4 << 20) // max(1, data[:1].nbytes)))
    return (rows,) + data.shape[1:]


def _is_aligned_artifact(path: Path) -> bool:
    try:
        attrs = zarr.open_group(str(path), mode="r").attrs
    except Exception:
        return False
    return "metric" in attrs and attrs.get("variant") in ALIGNED_VARIANTS
