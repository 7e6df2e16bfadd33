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
import yaml

from cli_inprocess import run_cli

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "benchmarks"))

import reflow_rounds  # noqa: E402


def test_paired_difference_cancels_the_seeds_difficulty():
    a, b = [0.9, 0.5, 0.1], [0.8, 0.4, 0.0]  # a is better by 0.1 on every seed
    d, se = reflow_rounds.paired(a, b)
    assert d == pytest.approx(0.1) and se == pytest.approx(0.0, abs=1e-12)
    d, se = reflow_rounds.paired([1.0, 0.0], [0.0, 1.0])
    assert d == 0.0 and se == pytest.approx(1.0)


def student_kind(row: Path) -> tuple[str, int]:
    """A row's recorded kind, and how many couplings its alignment replaced: an aligned student
    is SeFA only when that is more than none (issue 25; on the tiny flows here eps 0.1 and 0.2
    may replace nothing, and such a student is plain reflow)."""
    kind = json.loads((row / "checkpoints/latest/config.json").read_text())["kind"]
    summary = json.loads((row / "manifest.json").read_text())["summary"]
    return kind, (summary.get("alignment") or {}).get("n_replaced", 0)


def run_study_in_process(monkeypatch, capsys, *argv: str) -> str:
    """The study's main() with its `sefa` commands run in this process (tests/cli_inprocess.py):
    its 30-odd commands would otherwise spend most of their time importing torch in a child each.
    The first command (ingest) still runs in a real child, so the study's own runner is covered.
    Returns what the study printed."""
    child = reflow_rounds.sefa

    def sefa(ws: Path, *args: str, capture: bool = False) -> str:
        if args[0] == "ingest":
            return child(ws, *args, capture=capture)
        print("$ sefa " + " ".join(args))
        done = run_cli(*args, "-w", ws, cwd=REPO)
        assert done.returncode == 0, f"sefa {' '.join(args)}: {done.stderr[-3000:]}"
        return done.stdout

    monkeypatch.setattr(reflow_rounds, "sefa", sefa)
    monkeypatch.setattr(sys, "argv", ["reflow_rounds.py", *argv])
    reflow_rounds.main()
    return capsys.readouterr().out


def test_tiny_study_builds_every_row_and_reports_it(shared_data, tmp_path, monkeypatch, capsys):
    ws = tmp_path / "ws"
    out = run_study_in_process(
        monkeypatch, capsys, "-w", str(ws), "--rounds", "2", "--windows", "8", "--samples", "2",
        "--train-steps", "10", "--flow-steps", "10", "--student-steps", "10", "--n-test", "2",
        "--max-steps", "8", "--eps", "0.2", "--base-n-test", "3", "--eps-sweep", "0.1",
        "--k-sweep", "3", "--val-windows", "4")
    result = json.loads((ws / "rounds.json").read_text())
    rows = {(row["variant"], row["round"]): row for row in result["rows"]}
    assert set(rows) == {(v, k) for v in reflow_rounds.VARIANTS for k in (1, 2)}
    # round 1 of aligned_rounds is aligned_final's round 1; unaligned and aligned_final share
    # each round's couplings, so their drift is the same numbers
    assert rows[("aligned_rounds", 1)]["slug"] == "aligned_final_r1"
    assert rows[("unaligned", 2)]["drift"] == rows[("aligned_final", 2)]["drift"]
    for row in rows.values():
        assert len(row["per_seed"]) == 2 and row["nfe_per_solve"] > 1
        assert len(result["base_rk45"]["per_seed"]) == 3  # paired over the 2 seeds both ran
        d, _ = row["vs_base"]
        assert d == pytest.approx(np.mean(row["per_seed"]) - np.mean(result["base_rk45"]["per_seed"][:2]))
        kind, replaced = student_kind(ws / "rows" / row["slug"])
        assert kind == ("sefa_one_step" if row["variant"] != "unaligned" and replaced else
                        "reflow_one_step")
    # aligned_rounds round 2 trained on aligned couplings; the others did not
    manifest = json.loads((ws / "reflow/iter_2/manifest.json").read_text())
    assert manifest["summary"]["aligned_input"]["eps"] == 0.2
    assert "| aligned_rounds | 2 |" in out

    # the sweeps, on round 1: eps on the study's couplings, K on regenerated ones
    sweeps = {row["slug"]: row for row in result["sweeps"]}
    assert set(sweeps) == {"eps0.1_r1", "K3_unaligned_r1", "K3_aligned_r1"}
    assert sweeps["eps0.1_r1"]["drift"] == rows[("unaligned", 1)]["drift"]
    kind, replaced = student_kind(ws / "rows/eps0.1_r1")
    assert kind == ("sefa_one_step" if replaced else "reflow_one_step")
    assert sweeps["K3_unaligned_r1"]["drift"] == sweeps["K3_aligned_r1"]["drift"] != rows[("unaligned", 1)]["drift"]
    assert sweeps["K3_aligned_r1"]["vs_unaligned"][0] == pytest.approx(
        np.mean(sweeps["K3_aligned_r1"]["per_seed"]) - np.mean(sweeps["K3_unaligned_r1"]["per_seed"]))
    import zarr

    # the workspace is left at the study's own K
    assert zarr.open_group(str(ws / "reflow/iter_1/couplings.zarr"), mode="r").attrs["samples_per_window"] == 2


def test_base_from_continues_a_checkpoint_of_the_same_run_only(shared_data, tmp_path):
    """--base-from: a kept checkpoint of the preset's own run becomes the train stage without
    training (same weights); a checkpoint of another config is refused, naming what differs."""
    from argparse import Namespace

    from safetensors.torch import load_file

    first, second = tmp_path / "a", tmp_path / "b"
    args = Namespace(train_steps=6, samples=2, windows=8, flow_steps=4, student_steps=4, eps=0.1,
                     val_windows=None)
    first.mkdir()
    # the commands in-process through sefa_cli.main.main (tests/cli_inprocess.py)
    assert run_cli("ingest", shared_data / reflow_rounds.PUSHT_FILE, "--fps", "10", "--key",
                   "keypoint", "--key", "state", "--key", "action", "-w", first,
                   cwd=REPO).returncode == 0
    second.mkdir()
    subprocess.run(["cp", "-r", str(first / "dataset.zarr"), str(second)], check=True)
    for ws in (first, second):
        reflow_rounds.write_pipeline(ws, args)
    preset = str(REPO / "pipelines" / "pusht_lowdim_train.yaml")
    train = lambda ws, *extra: run_cli("train", preset, *reflow_rounds.train_overrides(args), *extra,
                                       "-w", ws, cwd=REPO)
    assert train(first).returncode == 0
    ckpt = first / "train" / "checkpoints" / "latest"
    reflow_rounds.seed_base(second, ckpt)
    done = train(second)
    assert done.returncode == 0 and "at step 6" in done.stdout + done.stderr
    a, b = (load_file(str(ws / "train/checkpoints/latest/ema.safetensors")) for ws in (first, second))
    assert all(torch_equal(a[k], b[k]) for k in a)

    other = tmp_path / "c"
    subprocess.run(["cp", "-r", str(second), str(other)], check=True)
    pipe = yaml.safe_load((other / "sefa.yaml").read_text())
    pipe["train"].append("training.lr=0.01")
    (other / "sefa.yaml").write_text(yaml.safe_dump(pipe))
    for stale in ("train", "runs"):
        subprocess.run(["rm", "-rf", str(other / stale)], check=True)
    with pytest.raises(SystemExit, match="training.lr"):
        reflow_rounds.seed_base(other, ckpt)


def torch_equal(a, b) -> bool:
    import torch

    return torch.equal(a, b)
