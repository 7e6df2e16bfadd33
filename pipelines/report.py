"""Plain-text reports of finished stages (what the CLI prints after them)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

QUANTILES = (0.0, 0.01, 0.1, 0.25, 0.5, 0.75, 0.9, 1.0)
# an eps that replaces less than this fraction, or more than 1 - it, is probably not meant
EXTREME = 0.01


def distance_quantiles(distance: np.ndarray) -> dict[str, float]:
    return {f"q{int(q * 100)}": float(np.quantile(distance, q)) for q in QUANTILES}


def eps_warning(fraction: float, eps: float, quantiles: dict[str, float],
                mean_distance: float | None = None) -> str | None:
    """A hint when eps replaces almost nothing or almost everything, or replaces chunks that are
    farther from the expert than the mean action is (`mean_distance`: the median distance of
    the expert chunks from their mean)."""
    found = []
    if fraction > 1 - EXTREME:
        found.append(f"warning: eps {eps:g} replaces {fraction:.1%} of the couplings (the largest "
                     f"distance is {quantiles['q100']:.3g}): the one-step policy then learns the "
                     f"expert chunks alone, as plain behaviour cloning; --eps "
                     f"{quantiles['q90']:.2g} keeps about 10% of the generated chunks")
    if mean_distance is not None and fraction >= EXTREME and eps > mean_distance:
        found.append(f"warning: eps {eps:g} replaces chunks up to {eps:.3g} from the expert's, "
                     f"farther than always predicting the mean action is (median "
                     f"{mean_distance:.3g}); the median coupling is {quantiles['q50']:.3g} away: "
                     f"the base flow's samples are not near the expert (the base flow is not "
                     f"trained enough: compare its validation action MSE with the mean action's, "
                     f"and train it longer), and alignment at this eps replaces chunks far from "
                     f"the expert rather than correcting near misses")
    if found:  # both may hold: every one is said, one line each
        return "\n".join(found)
    if fraction < EXTREME:
        return (f"warning: eps {eps:g} replaces {fraction:.1%} of the couplings: the smallest "
                f"distance is {quantiles['q0']:.3g}, the 10th percentile {quantiles['q10']:.3g}; "
                f"an eps near the distances you want replaced (e.g. --eps "
                f"{quantiles['q10']:.2g} for about 10%, or --eps auto) makes alignment do something")
    return None


def eps_words(summary: dict) -> str:
    """eps as the align stage chose it: `eps 0.05`, or `eps 0.0123, chosen to replace the
    nearest 20%`."""
    rule = summary.get("replace_fraction")
    return f"eps {summary['eps']:.4g}" + ("" if rule is None else
                                         f", chosen to replace the nearest {rule:.0%}")


def student_label(summary: dict) -> str:
    """A student as every table names it, from what its distill stage recorded: SeFA only when
    alignment replaced something, plain reflow when it did not or was not asked, and the
    method when it is not the reference code's (MSE at t = 0)."""
    from sefa_model.methods import student_label as named

    if summary.get("kind") == "one_step":  # distilled from the base flow: no couplings at all
        return named(summary.get("method"), None)
    a = summary.get("alignment")
    name = "SeFA one-step" if a and a.get("n_replaced") else "reflow one-step (no alignment)"
    if a and not a.get("n_replaced"):
        name = "reflow one-step (alignment replaced nothing)"
    return named(summary.get("method"), name)


def distill_alignment_line(alignment: dict) -> str:
    """What the student trains on, said before it trains: how much alignment replaced."""
    from sefa_model.sefa.alignment import AUTO_FRACTION

    frac, n, k = alignment["fraction_replaced"], alignment["n"], alignment["n_replaced"]
    head = f"distilling on the aligned couplings: {k} of {n} replaced ({frac:.1%}, {eps_words(alignment)})"
    if k == 0:
        return (f"{head}. Nothing was replaced, so this student is plain reflow and is labelled "
                f"reflow_one_step; `sefa align --eps auto` chooses an eps that replaces the "
                f"nearest {AUTO_FRACTION:.0%}")
    if frac < EXTREME:
        return f"{head}. warning: almost nothing was replaced, so this student is nearly plain reflow"
    return head


def alignment_report(align_dir: Path) -> str:
    """Fraction replaced, the distance histogram and quantiles, and a warning when eps replaces
    almost nothing or almost everything."""
    import zarr

    from sefa_model.sefa.alignment import format_histogram

    summary = json.loads((align_dir / "manifest.json").read_text())["summary"]
    distance = zarr.open_group(str(align_dir / "aligned.zarr"), mode="r")["distance"][:]
    q = distance_quantiles(distance)
    lines = [f"replaced {summary['fraction_replaced']:.1%} of {summary['n']} couplings "
             f"({eps_words(summary)}; {summary['metric']})",
             format_histogram(summary["histogram"], eps=summary["eps"]),
             "distance quantiles: " + ", ".join(f"{k} {v:.3g}" for k, v in q.items())]
    warning = eps_warning(summary["fraction_replaced"], summary["eps"], q,
                          summary.get("mean_action_distance"))
    if warning:
        lines.append(warning)
    return "\n".join(lines)
