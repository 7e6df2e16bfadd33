"""The reflow-rounds study's code (benchmarks/reflow_rounds.py, issue 11) on tiny checkpoints:
every variant and round is built through the CLI, its couplings' statistics are read back, and
the paired differences are computed over the same seeds. The study itself is not run in CI."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))

import reflow_rounds  # noqa: E402


def test_paired_difference_cancels_the_seeds_difficulty():
    a, b = [0.9, 0.5, 0.1], [0.8, 0.4, 0.0]  # a is better by 0.1 on every seed
    d, se = reflow_rounds.paired(a, b)
    assert d == pytest.approx(0.1) and se == pytest.approx(0.0, abs=1e-12)
    d, se = reflow_rounds.paired([1.0, 0.0], [0.0, 1.0])
    assert d == 0.0 and se == pytest.approx(1.0)


def test_tiny_study_builds_every_row_and_reports_it(shared_data, tmp_path):
    ws = tmp_path / "ws"
    r = subprocess.run([sys.executable, str(REPO / "benchmarks" / "reflow_rounds.py"), "-w", str(ws),
                        "--rounds", "2", "--windows", "8", "--samples", "2", "--train-steps", "10",
                        "--flow-steps", "10", "--student-steps", "10", "--n-test", "2",
                        "--max-steps", "8", "--eps", "0.2"],
                       cwd=REPO, capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-3000:]
    result = json.loads((ws / "rounds.json").read_text())
    rows = {(row["variant"], row["round"]): row for row in result["rows"]}
    assert set(rows) == {(v, k) for v in reflow_rounds.VARIANTS for k in (1, 2)}
    # round 1 of aligned_rounds is aligned_final's round 1; unaligned and aligned_final share
    # each round's couplings, so their drift is the same numbers
    assert rows[("aligned_rounds", 1)]["slug"] == "aligned_final_r1"
    assert rows[("unaligned", 2)]["drift"] == rows[("aligned_final", 2)]["drift"]
    for row in rows.values():
        assert len(row["per_seed"]) == 2 and row["nfe_per_solve"] > 1
        d, _ = row["vs_base"]
        assert d == pytest.approx(np.mean(row["per_seed"]) - np.mean(result["base_rk45"]["per_seed"]))
        kind = json.loads((ws / "rows" / row["slug"] / "checkpoints/latest/config.json").read_text())["kind"]
        assert kind == ("reflow_one_step" if row["variant"] == "unaligned" else "sefa_one_step")
    # aligned_rounds round 2 trained on aligned couplings; the others did not
    manifest = json.loads((ws / "reflow/iter_2/manifest.json").read_text())
    assert manifest["summary"]["aligned_input"]["eps"] == 0.2
    assert "| aligned_rounds | 2 |" in r.stdout
