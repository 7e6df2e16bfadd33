"""Selective flow alignment: snap generated action chunks to the expert's when they are close.

The reflow stage integrates the base policy's ODE from noise z0 to a generated chunk z1 for
every training window, several times per window (the *couplings*). Alignment replaces z1 by
the expert chunk of the same observation **only when z1 already lies within eps of it**.
Replacing every z1 would pair random noise with the ground truth, i.e. plain regression to the
mean; keeping the far ones preserves the modes the base policy found. z0 is never changed.

Metric (as the reference code's `find_nearest.py`): the mean over the horizon of the per-step
L2 norm over the action dimensions, ``d = mean_t ||gen_t - exp_t||_2``, computed here in
normalized action space (the reference computes it in raw units, which equal normalized units
on Meta-World only).

Two variants:

* ``same_window``: the candidate is the expert chunk of the coupling's own training window.
* ``matching_obs``: the reference code's search. The candidates are the expert chunks of every
  training window whose observation matches the coupling's within `tol` (max-abs difference of
  the frozen base encoder's features: the normalized observation as the policy sees it for
  low-dim keys, the image features for cameras); the own window always matches. The nearest candidate
  replaces when within eps. The reference screens by action distance first and then takes the
  window with the nearest *observation*; here the nearest *action* among matching observations
  is taken. Both replace exactly the same couplings; they can differ only in which of several
  same-observation expert chunks is used.

Choosing eps from the data (`replace_fraction`): the paper's eps (0.1, the reference code's,
or 0.05) is in Meta-World's raw action units; in our normalized units it can lie far below
every coupling's distance, and then alignment replaces nothing and the student is plain reflow.
With `replace_fraction` F the eps is the smallest one that replaces the nearest F of the
couplings (`eps_for_fraction`), recorded in the artifact beside the fraction it replaced.

Not reproduced from the reference code (sefa-method.md 1.8): zero-padded demos (our sampler
repeats edge frames, so no zero-action windows exist), and the `None` it returns when the best
match is at distance exactly 0.

Artifacts: couplings are read and the aligned set written by `sefa_model.data.couplings`, which also
owns the metric (`chunk_distance`), shared with reflow's report of the expert drift.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Iterator, Literal, NamedTuple

import numpy as np

from sefa_data.errors import SefaInputError
from sefa_model.data.couplings import (ALIGNED_VARIANTS, METRIC, PROVENANCE_KEYS, Couplings,
                                  chunk_distance, read_couplings, write_aligned)
from sefa_model.progress import report

Variant = Literal["same_window", "matching_obs"]
VARIANTS = ALIGNED_VARIANTS

# `sefa align --eps auto`: replace the nearest 20 % of the couplings. On the Push-T profile
# (docs/results/pusht.md) eps 0.05 replaced about 22 % (the rounds study's round 1) and scored best of
# eps 0.02, 0.05, 0.1 and 0.2; the larger ones, replacing more, scored below plain reflow.
AUTO_FRACTION = 0.2

# Work arrays of the blocked searches stay around this many float64 elements (32 MB).
DEFAULT_BLOCK_ELEMS = 1 << 22
# A screen with more observation pairs than this means tol is too loose for the data.
DEFAULT_MAX_PAIRS = 50_000_000


# --------------------------------------------------------------------------- the metric


def mean_action_distance(expert: np.ndarray) -> float:
    """The median distance of the expert chunks (N, T, Da) from their mean chunk: how far a
    policy that always predicts the mean action is from the expert, in the alignment metric."""
    if not len(expert):
        return float("nan")
    mean = np.broadcast_to(np.asarray(expert, np.float64).mean(axis=0), expert.shape)
    return float(np.median(chunk_distance(expert, mean)))


def select_targets(generated: np.ndarray, expert: np.ndarray, eps: float
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The same-window rule: (target, replaced, distance).

    replaced = distance < eps, strictly, so eps = 0 replaces nothing; target is the expert chunk
    where replaced, the generated one elsewhere (float32).
    """
    _check_eps(eps)
    distance = chunk_distance(generated, expert)
    replaced = distance < eps
    target = np.where(replaced[:, None, None], expert, generated).astype(np.float32)
    return target, replaced, distance


def eps_for_fraction(distance: np.ndarray, fraction: float) -> float:
    """The smallest eps that replaces at least `fraction` of the couplings: the nearest ones.

    With k = ceil(fraction * M), eps is the next float32 above the k-th smallest distance (the
    rule is distance < eps, strictly, on float32 distances), so exactly the couplings at or
    below that distance are replaced; ties with it are all replaced. fraction 0 gives eps 0.
    """
    if not (isinstance(fraction, (int, float, np.floating)) and 0 <= fraction <= 1):
        raise ValueError(f"fraction must be in [0, 1], got {fraction!r}")
    d = np.sort(np.asarray(distance, np.float32).ravel())
    k = math.ceil(fraction * len(d) - 1e-9)  # 0.2 * 100 is 20, not 21, in floating point
    if k == 0:
        return 0.0
    return float(np.nextafter(d[k - 1], np.float32(np.inf)))


# --------------------------------------------------------------------------- matching observations


class Candidates(NamedTuple):
    """For each window i, the windows whose observation matches i's, in CSR form:
    ``indices[indptr[i]:indptr[i + 1]]``, ascending, i itself included.

    "Matches" is max-abs difference <= tol, inclusive (unlike eps), so tol = 0 means identical.
    """

    indptr: np.ndarray  # (N + 1,) int64
    indices: np.ndarray  # (nnz,) int64

    def of(self, i: int) -> np.ndarray:
        return self.indices[self.indptr[i]:self.indptr[i + 1]]

    @property
    def counts(self) -> np.ndarray:
        return np.diff(self.indptr)


def matching_obs_candidates(obs_features: np.ndarray, tol: float, *,
                            block_elems: int = DEFAULT_BLOCK_ELEMS,
                            max_pairs: int = DEFAULT_MAX_PAIRS) -> Candidates:
    """All pairs of windows whose features differ by at most `tol` in every element.

    obs_features: (N, ...) normalized observation features per window, flattened to (N, D).

    Sort-and-sweep rather than an N x N matrix: sort the windows along the feature dimension
    that leaves the fewest pairs within tol (one sort + searchsorted per dimension), so that the
    windows within tol of one another along it are a contiguous run of the sorted order. Each
    such pair is then checked dimension by dimension, the most selective first, dropping the
    pairs that fail as it goes. Exact for any tol: no rounding into bins.

    Cost: O(D N log N) to rank the dimensions, then O(P) per checked dimension for the P pairs
    of the sweep, shrinking as pairs fail; memory O(block_elems) per block. On Push-T
    (N = 21.7k, D = 46) tol = 1e-3 sweeps 0.3M pairs, tol = 0.05 sweeps 15M, both in about a
    second. P approaches N^2 / 2 only when many windows really share an observation (or tol is
    loose); beyond `max_pairs` a SefaInputError says so rather than running out of memory.
    """
    f = np.asarray(obs_features, np.float64)
    f = f.reshape(len(f), -1)
    n, d = f.shape
    if d == 0:
        raise ValueError("obs_features has no feature dimension")
    if not (tol >= 0 and math.isfinite(tol)):
        raise ValueError(f"tol must be finite and >= 0, got {tol}")
    # A float64 rounding of key +- tol must not lose a pair that the exact check keeps.
    slack = tol + 4 * np.finfo(np.float64).eps * float(np.abs(f).max(initial=0.0))

    axes, pairs = _axes_by_selectivity(f, slack)
    if pairs > max_pairs:
        raise SefaInputError(
            f"{pairs} pairs of windows have observations within tol={tol:g} on their most "
            f"distinct feature (limit {max_pairs}); lower tol, or use variant same_window",
            key="obs_features")
    columns = np.ascontiguousarray(f[:, axes].T)  # one contiguous row per dimension to check
    order = np.argsort(columns[0], kind="stable")
    key = columns[0][order]
    # each unordered pair once: from the earlier of the two in sorted order
    after = np.arange(1, n + 1)
    hi = np.searchsorted(key, key + slack, "right")

    rows, cols = [np.arange(n)], [np.arange(n)]  # every window matches itself
    for a, b in _blocks(hi - after, block_elems):
        p, q = _expand(np.arange(a, b), after[a:b], hi[a:b] - after[a:b])
        i, j = order[p], order[q]
        for column in columns:
            keep = np.abs(column[i] - column[j]) <= tol
            i, j = i[keep], j[keep]
        rows += [i, j]
        cols += [j, i]
    rows_all, cols_all = np.concatenate(rows), np.concatenate(cols)
    by_row = np.lexsort((cols_all, rows_all))
    indptr = np.concatenate([[0], np.cumsum(np.bincount(rows_all, minlength=n))])
    return Candidates(indptr.astype(np.int64), cols_all[by_row].astype(np.int64))


def _axes_by_selectivity(f: np.ndarray, slack: float) -> tuple[np.ndarray, int]:
    """The feature dimensions, fewest pairs within `slack` first, and the pair count (each
    unordered pair once) of the first."""
    pairs = np.empty(f.shape[1], np.int64)
    for axis in range(f.shape[1]):
        key = np.sort(f[:, axis])
        later = np.searchsorted(key, key + slack, "right") - np.arange(1, len(key) + 1)
        pairs[axis] = later.sum()
    axes = np.argsort(pairs, kind="stable")
    return axes, int(pairs[axes[0]])


def select_targets_matching_obs(generated: np.ndarray, window: np.ndarray,
                                expert_by_window: np.ndarray, obs_features: np.ndarray | None,
                                eps: float, tol: float, *, candidates: Candidates | None = None,
                                block_elems: int = DEFAULT_BLOCK_ELEMS
                                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The reference code's rule: (target, replaced, distance, nearest).

    generated (M, T, Da), window (M,) -> rows of expert_by_window (N, T, Da) and of
    obs_features (N, ...). For each coupling, `nearest` is the window, among those whose
    observation matches its own within tol, whose expert chunk is nearest to the generated one
    (the own window on ties); `distance` is that chunk's distance. replaced = distance < eps.

    Since the own window is always a candidate, distance is never larger than same_window's and
    the replaced set is a superset of it. Pass `candidates` to reuse a matching_obs_candidates
    result (then obs_features and tol are not used). Cost: O(Q T Da) for the Q = sum over
    couplings of their window's candidate count, in blocks of about `block_elems` elements.
    Q is about M for distinct observations; a group of G windows sharing one observation adds
    about K G^2 (e.g. 1,000 identical windows with K = 10 samples: 10M chunk distances, ~10 s).
    """
    _check_eps(eps)
    generated = np.asarray(generated)
    expert = np.asarray(expert_by_window)
    window = np.asarray(window, np.int64)
    if candidates is None:
        if obs_features is None:
            raise ValueError("give obs_features (or precomputed candidates)")
        candidates = matching_obs_candidates(obs_features, tol, block_elems=block_elems)
    m = len(generated)
    nearest = np.empty(m, np.int64)
    distance = np.empty(m, np.float32)
    counts = candidates.counts[window]
    if (counts == 0).any():
        raise ValueError("every window must be among its own candidates")
    per_pair = generated[0].size if m else 1
    for a, b in _blocks(counts * per_pair, block_elems):
        w = window[a:b]
        seg, at = _expand(np.arange(b - a), candidates.indptr[w], counts[a:b])
        col = candidates.indices[at]
        d = chunk_distance(generated[a:b][seg], expert[col])
        # within each coupling: nearest first, the own window first among equals
        order = np.lexsort((col != w[seg], d, seg))
        best = order[np.cumsum(counts[a:b]) - counts[a:b]]
        nearest[a:b], distance[a:b] = col[best], d[best]
    replaced = distance < eps
    target = np.where(replaced[:, None, None], expert[nearest], generated).astype(np.float32)
    return target, replaced, distance, nearest


def _expand(owner: np.ndarray, start: np.ndarray, count: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray]:
    """Flatten the runs [start[k], start[k] + count[k]) into (owner of each element, element)."""
    total = int(count.sum())
    first = np.cumsum(count) - count
    offset = np.arange(total, dtype=np.int64) - np.repeat(first, count)
    return np.repeat(owner, count), np.repeat(start, count) + offset


def _blocks(cost: np.ndarray, budget: int) -> Iterator[tuple[int, int]]:
    """Consecutive ranges [a, b) whose summed cost stays within budget (at least one item)."""
    csum = np.cumsum(cost)
    a = 0
    while a < len(cost):
        base = csum[a - 1] if a else 0
        b = max(a + 1, int(np.searchsorted(csum, base + budget, "right")))
        yield a, b
        report("align", b, len(cost))
        a = b


# --------------------------------------------------------------------------- reporting


def distance_histogram(distance: np.ndarray, bins: int = 20) -> dict[str, list]:
    """{"edges": bins + 1 floats, "counts": bins ints} over [0, max distance].

    Non-finite distances are left out; an all-zero (or empty) input gets the range [0, 1].
    """
    d = np.asarray(distance, np.float64)
    d = d[np.isfinite(d)]
    top = float(d.max()) if len(d) and d.max() > 0 else 1.0
    counts, edges = np.histogram(d, bins=bins, range=(0.0, top))
    return {"edges": [float(e) for e in edges], "counts": [int(c) for c in counts]}


def format_histogram(hist: dict[str, list], width: int = 40, eps: float | None = None) -> str:
    """One line per bin: its range, its count and a bar; `eps` marks the bin it falls in."""
    edges, counts = hist["edges"], hist["counts"]
    peak = max(counts, default=0) or 1
    digits = len(str(max(counts, default=0)))
    lines = []
    for k, c in enumerate(counts):
        lo, hi = edges[k], edges[k + 1]
        close = "]" if k == len(counts) - 1 else ")"
        bar = "#" * round(width * c / peak)
        mark = f"  <- eps={eps:g}" if eps is not None and lo <= eps < hi else ""
        lines.append(f"[{lo:8.4f}, {hi:8.4f}{close} {c:>{digits}} {bar}{mark}")
    return "\n".join(lines)


# --------------------------------------------------------------------------- the stage


def align(couplings_path: str | Path, expert_chunks: np.ndarray, out_path: str | Path,
          eps: float, variant: Variant = "same_window", obs_features: np.ndarray | None = None,
          tol: float = 1e-3, replace_fraction: float | None = None) -> dict[str, Any]:
    """Align the couplings at `couplings_path` and write the aligned artifact to `out_path`.

    expert_chunks: (N, T, Da) normalized expert action chunks, row w = training window w (the
    `window` indices of the couplings). obs_features: (N, ...) normalized observation features
    per window, needed by variant matching_obs. replace_fraction: choose eps from the distances
    (`eps_for_fraction`) instead of using `eps`. Returns a summary (the artifact's attrs).
    """
    file = str(couplings_path)
    try:
        _check_eps(eps)
        if replace_fraction is not None:
            eps_for_fraction(np.zeros(0, np.float32), replace_fraction)  # checks the range
    except ValueError as e:
        raise SefaInputError(str(e), key="eps" if replace_fraction is None
                             else "replace_fraction") from None
    if variant not in VARIANTS:
        raise SefaInputError(f"unknown variant '{variant}' (use one of {', '.join(VARIANTS)})",
                             key="variant")
    if Path(out_path).resolve() == Path(couplings_path).resolve():
        raise SefaInputError("the output would overwrite the couplings", file=str(out_path))
    c = read_couplings(couplings_path)
    expert = _check_expert(expert_chunks, c, file)

    # first every coupling's distance to its nearest candidate; then eps; then the replacement
    extra: dict[str, Any] = {}
    if variant == "same_window":
        nearest = c.window
        distance = chunk_distance(c.action, expert[c.window])
    else:
        features = _check_obs_features(obs_features, len(expert), tol)
        _, _, distance, nearest = select_targets_matching_obs(
            c.action, c.window, expert, features, 0.0, tol)
    if replace_fraction is not None:
        eps = eps_for_fraction(distance, replace_fraction)
        _check_near_misses(eps, replace_fraction, mean_action_distance(expert), file)
    replaced = distance < eps
    target = np.where(replaced[:, None, None], expert[nearest], c.action).astype(np.float32)
    if variant == "matching_obs":
        extra = {"tol": float(tol),
                 "replaced_from_other_window": int((replaced & (nearest != c.window)).sum())}

    hist = distance_histogram(distance)
    attrs = {"eps": float(eps), "metric": METRIC, "variant": variant,
             # how far the expert chunks lie from their mean (the median): what a policy that
             # always predicted the mean action would be off by, to judge eps and the distances
             "mean_action_distance": mean_action_distance(expert),
             # how eps was chosen: given, or the smallest replacing this fraction
             "replace_fraction": None if replace_fraction is None else float(replace_fraction),
             "fraction_replaced": float(replaced.mean()), "histogram": hist, "n": len(target),
             "n_replaced": int(replaced.sum()), **extra,
             "couplings": file, "couplings_attrs": _jsonable(c.attrs),
             # the aligned targets live in the couplings' space: their provenance carries over
             **{k: _jsonable(c.attrs[k]) for k in PROVENANCE_KEYS if k in c.attrs}}
    write_aligned(out_path, {"noise": c.noise, "target": target, "window": c.window,
                             "replaced": replaced, "distance": distance}, attrs)
    return {**attrs, "path": str(out_path)}


def align_to_expert(checkpoint: Path, store: Path, couplings: Path, out: Path, eps: float, *,
                    variant: Variant = "same_window", tol: float = 1e-3, device: str = "auto",
                    features_cache: Path | None = None,
                    replace_fraction: float | None = None) -> dict[str, Any]:
    """`align` against the expert chunks of the store's training windows, in the normalized
    space of the base policy at `checkpoint` (the couplings' own space); for matching_obs, its
    encoder's view of every window (dims slices, normalization and, for images, features)."""
    from sefa_data.store.zarr_store import EpisodeStore
    from sefa_model.data.features import cached_window_features
    from sefa_model.policy.artifact import Policy
    from sefa_model.data.windows import PolicyData

    policy = Policy.load(checkpoint, device=device)
    data = PolicyData(policy.cfg, EpisodeStore.open(store), policy.normalizer)
    windows = np.arange(len(data.train))
    obs_features = None
    if variant == "matching_obs":
        obs_features = cached_window_features(policy.model, data, windows, policy.device,
                                              features_cache).numpy()
    return align(couplings, data.expert_chunks(windows), out, eps, variant=variant,
                 obs_features=obs_features, tol=tol, replace_fraction=replace_fraction)


def _check_near_misses(eps: float, fraction: float, mean_distance: float, file: str) -> None:
    """eps chosen from the data must pick near misses: when even the nearest `fraction` of the
    couplings lie farther from their expert chunks than always predicting the mean action
    does (the median distance of the expert chunks from their mean), the base flow's samples
    are not near the expert (it is not trained enough) and replacing them would teach the
    student the expert's chunks for noises the flow maps elsewhere. One line, nothing written;
    a fixed eps (a number) still aligns, with the warning `sefa align` prints."""
    if math.isfinite(mean_distance) and eps > mean_distance and fraction > 0:
        raise SefaInputError(
            f"the nearest {fraction:.0%} of the couplings lie up to {eps:.3g} from the expert's "
            f"chunks, farther than always predicting the mean action ({mean_distance:.3g}, the "
            f"median): the base flow is not trained enough for alignment to correct near "
            f"misses; train it longer (its validation action MSE should be well below the mean "
            f"action's), or align at a fixed eps anyway (--eps E)", file=file,
            key="replace_fraction")


def _check_eps(eps: float) -> None:
    if not (isinstance(eps, (int, float, np.floating, np.integer)) and eps >= 0):
        raise ValueError(f"eps must be a number >= 0, got {eps!r}")


def _check_expert(expert_chunks: np.ndarray, c: Couplings, file: str) -> np.ndarray:
    expert = np.asarray(expert_chunks)
    if expert.ndim != 3 or expert.shape[1:] != c.action.shape[1:]:
        raise SefaInputError(f"expert chunks have shape {expert.shape}, the couplings' chunks "
                             f"{c.action.shape[1:]} (need (N_windows, T, Da))",
                             file=file, key="action")
    if not np.isfinite(expert).all():
        raise SefaInputError("NaN or Inf in the expert chunks", key="expert_chunks")
    lo, hi = int(c.window.min()), int(c.window.max())
    if lo < 0 or hi >= len(expert):
        bad = int(np.flatnonzero((c.window < 0) | (c.window >= len(expert)))[0])
        raise SefaInputError(f"window index {int(c.window[bad])} outside the {len(expert)} "
                             f"training windows (are the couplings from another store or "
                             f"sampler setting?)", file=file, key="window",
                             where=f"coupling {bad}")
    return expert.astype(np.float32, copy=False)


def _check_obs_features(obs_features: np.ndarray | None, n_windows: int, tol: float
                        ) -> np.ndarray:
    if obs_features is None:
        raise SefaInputError("variant matching_obs needs obs_features", key="obs_features")
    f = np.asarray(obs_features)
    if len(f) != n_windows or f.ndim < 2 or f[0].size == 0:
        raise SefaInputError(f"shape {f.shape}, need ({n_windows}, D) for the {n_windows} "
                             f"training windows", key="obs_features")
    if not np.isfinite(f).all():
        raise SefaInputError("NaN or Inf", key="obs_features")
    if not (isinstance(tol, (int, float, np.floating)) and math.isfinite(tol) and tol >= 0):
        raise SefaInputError(f"tol must be finite and >= 0, got {tol!r}", key="tol")
    return f


def _jsonable(value: Any) -> Any:
    """Numpy scalars and arrays in zarr attrs become plain JSON values."""
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    return value
