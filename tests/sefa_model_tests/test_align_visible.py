"""Alignment that replaces nothing is visible downstream, and eps can be chosen from the data
(issue 25, trap 3), through the real `sefa` command on the KUKA MCAP workspace (a tiny flow,
16 windows x 2 couplings).

- `sefa distill` says what fraction alignment replaced; with nothing replaced its student is
  labelled plain reflow (`reflow_one_step`), and `sefa status` says so;
- `sefa align --eps auto` on a flow whose samples are farther from the expert than the mean
  action stops in one line; the eps it names replaces the nearest AUTO_FRACTION of the
  couplings, and the student is SeFA's.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import zarr

from sefa_inprocess import kuka_workspace, sefa
from sefa_model.sefa.alignment import AUTO_FRACTION, eps_for_fraction


@pytest.fixture(scope="module")
def ws(shared_data, tmp_path_factory) -> Path:
    ws = kuka_workspace(shared_data, tmp_path_factory.mktemp("kuka_align"))
    sefa("reflow", "--max-windows", "16", "--samples", "2", "--threads", "1", "-w", ws)
    return ws


def kind(ws: Path) -> str:
    return json.loads((ws / "distill/checkpoints/latest/config.json").read_text())["kind"]


def status_row(ws: Path, stage: str) -> dict:
    rows = json.loads(sefa("status", "--json", "-w", ws).stdout)["rows"]
    return next(r for r in rows if r["stage"] == stage)


def test_a_student_whose_alignment_replaced_nothing_is_plain_reflow_and_says_so(ws):
    sefa("align", "--eps", "0", "-w", ws)
    r = sefa("distill", "--threads", "1", "-w", ws)
    assert ("distilling on the aligned couplings: 0 of 32 replaced (0.0%, eps 0). Nothing was "
            "replaced, so this student is plain reflow and is labelled reflow_one_step") in r.stderr
    assert kind(ws) == "reflow_one_step"
    summary = json.loads((ws / "distill/manifest.json").read_text())["summary"]
    assert summary["kind"] == "reflow_one_step" and summary["alignment"]["n_replaced"] == 0
    assert "aligned 0% (eps 0): plain reflow" in status_row(ws, "distill")["metric"]


def test_eps_auto_on_an_untrained_flow_stops_and_its_eps_as_a_number_replaces_the_nearest(ws):
    """This 20-step flow's samples lie farther from the expert than the mean action does:
    `--eps auto` stops in one line, writing nothing (it went ahead while its own warning said
    the flow was untrained). The eps it would have chosen, given as a number, replaces the
    nearest 20 % (7 of 32) and the student is SeFA's."""
    runs_before = sorted(p.name for p in (ws / "runs").glob("align/*"))
    bad = sefa("align", "--eps", "auto", "-w", ws, ok=False)
    assert bad.returncode == 1 and bad.stderr.count("error: ") == 1, bad.stderr
    assert ("replace_fraction: the nearest 20% of the couplings lie up to " in bad.stderr
            and "the base flow is not trained enough" in bad.stderr)
    assert sorted(p.name for p in (ws / "runs").glob("align/*")) == runs_before
    sefa("align", "--eps", "0", "-w", ws)  # every distance, nothing replaced
    d = zarr.open_group(str(ws / "align/aligned.zarr"), mode="r")["distance"][:]
    eps = eps_for_fraction(d, AUTO_FRACTION)
    assert f"lie up to {eps:.3g} from the expert's chunks" in bad.stderr
    sefa("align", "--eps", repr(eps), "-w", ws)
    aligned = zarr.open_group(str(ws / "align/aligned.zarr"), mode="r")
    replaced = aligned["replaced"][:]
    n = math.ceil(AUTO_FRACTION * len(d))  # the nearest 20 %: 7 of 32
    assert replaced.sum() == n == aligned.attrs["n_replaced"]
    np.testing.assert_array_equal(replaced, d < eps)
    assert d[replaced].max() < d[~replaced].min()  # the nearest ones
    assert f"eps {eps:.4g}" in status_row(ws, "align")["metric"]

    r = sefa("distill", "--threads", "1", "-w", ws)
    assert f"distilling on the aligned couplings: {n} of 32 replaced" in r.stderr
    assert kind(ws) == "sefa_one_step"
    assert f"aligned {n / 32:.1%} (eps {eps:.4g})" in status_row(ws, "distill")["metric"]

    # a number again clears the fraction kept from --eps auto
    sefa("align", "--eps", "0.05", "-w", ws)
    assert zarr.open_group(str(ws / "align/aligned.zarr"), mode="r").attrs["eps"] == 0.05
    bad = sefa("align", "--eps", "banana", "-w", ws, ok=False)
    assert bad.returncode == 1 and bad.stderr == "error: --eps: 'banana' is neither a number nor auto\n"


def test_eps_for_fraction_on_ties_and_the_ends():
    d = np.array([0.3, 0.1, 0.1, 0.2], np.float32)
    assert eps_for_fraction(d, 0) == 0.0
    assert (d < eps_for_fraction(d, 0.25)).sum() == 2  # the tie at 0.1 goes in with it
    assert (d < eps_for_fraction(d, 0.75)).sum() == 3
    assert (d < eps_for_fraction(d, 1.0)).all()
