"""No broken setting reaches a run (issue 23), through the real `sefa` command: a pipeline file
that does not exist is an error and sefa.yaml is never rewritten without --save (which keeps a
backup); a refused command writes nothing; every bad value (NaN, infinities, 0, negatives, a
batch larger than the data or the memory) is one line naming the key as typed, exit 1, before
any data is loaded or anything is written; `train --out` trains with the workspace's settings.

The refusals run in-process through `sefa_cli.main.main` (tests/cli_inprocess.py: the same parsing,
checks, line and exit status, without a child's ~3.5 s of imports); one bad value and the
training of `train --out` still run in a real child process.
"""

from __future__ import annotations

import dataclasses
import fcntl
import json
import math
import os
import shutil
import subprocess
import sys
import typing
from pathlib import Path

import pytest
import yaml

from cli_inprocess import run_cli

REPO = Path(__file__).resolve().parents[2]
TUNED = {"train": ["policy.head=mlp", "policy.mlp_hidden_dims=[8,8]", "policy.time_embed_dim=8",
                   "training.max_steps=7"],
         "reflow": {"iters": 2, "samples_per_window": 3}}


def sefa(ws: Path, *args) -> subprocess.CompletedProcess:
    """`sefa ARGS -w WS` in-process (tests/cli_inprocess.py), run from the workspace's parent."""
    return run_cli(*args, "-w", ws, cwd=ws.parent)


def sefa_child(ws: Path, *args) -> subprocess.CompletedProcess:
    """The same in a real child process: for the entry point itself and for training."""
    return subprocess.run([sys.executable, "-m", "sefa_cli.main", *map(str, args), "-w", str(ws)],
                          capture_output=True, text=True, cwd=ws.parent,
                          env={**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"},
                          timeout=300)  # a check that broke starts a long run: fail, not hang


def snapshot(ws: Path) -> dict[str, bytes]:
    """Every file of the workspace but the store (which no command here may touch either, but
    is large): sefa.yaml, .sefa/, runs/, pointers."""
    return {str(p.relative_to(ws)): p.read_bytes() for p in sorted(ws.rglob("*"))
            if p.is_file() and "dataset.zarr" not in p.parts}


def one_error_line(r: subprocess.CompletedProcess, *fragments: str) -> str:
    assert r.returncode == 1, (r.stdout, r.stderr[-2000:])
    assert "Traceback" not in r.stderr, r.stderr
    errors = [line for line in r.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1, r.stderr
    for f in fragments:
        assert f in errors[0], errors[0]
    return errors[0]


@pytest.fixture(scope="module")
def store(shared_data, tmp_path_factory) -> Path:
    ws = tmp_path_factory.mktemp("store")
    r = sefa(ws, "ingest", shared_data / "pusht_cchi_v7_replay.zarr", "--fps", "10",
             "--key", "keypoint", "--key", "state", "--key", "action")
    assert r.returncode == 0, r.stderr
    return ws / "dataset.zarr"


@pytest.fixture(scope="module")
def tuned_ws(store, tmp_path_factory) -> Path:
    """A workspace with a tuned sefa.yaml and kept command-line settings; the bad-value cases
    only read it (each must leave it as it was)."""
    ws = tmp_path_factory.mktemp("tuned") / "ws"
    ws.mkdir()
    shutil.copytree(store, ws / "dataset.zarr")
    (ws / "sefa.yaml").write_text(yaml.safe_dump(TUNED, sort_keys=False))
    (ws / ".sefa").mkdir()
    (ws / ".sefa" / "flags.yaml").write_text(yaml.safe_dump({"align": {"eps": 0.05}}))
    return ws


# --- sefa.yaml is never lost ----------------------------------------------------------------------

def test_run_with_a_missing_pipeline_file_is_an_error_and_keeps_sefa_yaml(tuned_ws):
    before = snapshot(tuned_ws)
    r = sefa(tuned_ws, "run", "nope.yaml")
    one_error_line(r, "nope.yaml", "no such pipeline file")
    assert snapshot(tuned_ws) == before  # sefa.yaml byte-identical, no runs, flags kept


def test_run_with_other_settings_needs_save_which_keeps_a_backup(tmp_path):
    ws = tmp_path / "ws"  # no store: the run stops before it keeps anything (issue 25)
    ws.mkdir()
    tuned = yaml.safe_dump(TUNED, sort_keys=False)
    (ws / "sefa.yaml").write_text(tuned)
    (tmp_path / "other.yaml").write_text(yaml.safe_dump({"reflow": {"iters": 1}}))
    before = snapshot(ws)
    r = sefa(ws, "run", tmp_path / "other.yaml")
    one_error_line(r, "sefa.yaml", "other.yaml", "--save", "here")
    assert snapshot(ws) == before
    r = sefa(ws, "run", tmp_path / "other.yaml", "--save")
    one_error_line(r, "dataset.zarr", "no episode store", "`sefa ingest RECORDINGS")
    assert snapshot(ws) == before  # a refused command keeps nothing (the .bak: below)


def test_a_command_refused_by_the_lock_writes_nothing(tuned_ws):
    lock = tuned_ws / ".sefa" / "lock"
    fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        os.pwrite(fd, b"4242", 0)
        before = snapshot(tuned_ws)
        r = sefa(tuned_ws, "train", "training.max_steps=30")
        one_error_line(r, "holds the workspace lock")
        assert snapshot(tuned_ws) == before  # flags.yaml not rewritten: status sees no change
        r = sefa(tuned_ws, "align", "--eps", "0.2", "--save", "--yes")
        one_error_line(r, "holds the workspace lock")
        assert snapshot(tuned_ws) == before  # sefa.yaml not rewritten either
        # refused for unconfirmed upstream work: nothing kept either
        r = sefa(tuned_ws, "align", "--eps", "0.2")
        one_error_line(r, "`sefa align` must first run train")
        assert snapshot(tuned_ws) == before
    finally:
        os.close(fd)
        lock.unlink()


# --- every bad value: one line naming the key, nothing written -----------------------------------

BAD = [
    # (command line, what the error line must name)
    (["align", "--eps", "nan"], "--eps: nan is not a finite number"),
    (["align", "--eps", "inf"], "--eps: inf is not a finite number"),
    (["align", "--eps", "-0.1"], "--eps: -0.1 is too small"),
    (["train", "training.lr=nan"], "training.lr: nan"),
    (["train", "training.lr=.inf"], "training.lr: inf"),
    (["train", "training.ema_power=nan"], "training.ema_power: nan"),
    (["train", "training.val_every=0"], "training.val_every: 0 is too small"),
    (["train", "training.max_steps=0"], "training.max_steps: 0 is too small"),
    (["train", "training.batch_size=0"], "training.batch_size: 0 is too small"),
    (["train", "training.batch_size=100000000"], "training.batch_size: 100000000 is more than"),
    (["train", "policy.head=unet", "policy.down_dims=[4096,8192,16384]",
      "training.batch_size=20000"], "training.batch_size: 20000 samples need at least"),
    (["train", "policy.down_dims=[256,0]"], "policy.down_dims[1]: 0 is too small"),
    (["train", "training.betas=[0.9,1.5]"], "training.betas[1]: 1.5 is too large"),
    (["reflow", "--samples", "0"], "--samples: 0 is too small"),
    (["reflow", "--max-windows", "0"], "--max-windows: 0 is too small"),
    (["reflow", "--max-windows", "-1"], "--max-windows: -1 is too small"),
    (["reflow", "--iters", "0"], "--iters: 0 is too small"),
    (["reflow", "--iters", "-1"], "--iters: -1 is too small"),
    (["eval", "--offline", "--windows", "0"], "--windows: 0 is too small"),
    (["eval", "--offline", "--samples", "0"], "--samples: 0 is too small"),
    (["eval", "--offline", "--steps", "0"], "--steps: 0 is too small"),
    (["eval", "--offline", "--steps", "-1"], "--steps: -1 is too small"),
    (["eval", "--env", "pusht", "--n-test", "0"], "--n-test: 0 is too small"),
    (["eval", "--env", "pusht", "--n-test", "-1"], "--n-test: -1 is too small"),
    (["export", "train", "--out", "exported", "--steps", "0"], "--steps: 0 is too small"),
    (["export", "train", "--out", "exported", "--fps", "nan"], "--fps: nan is not a finite"),
]


def cli(*args) -> subprocess.CompletedProcess:
    """`sefa ARGS` in-process (tests/cli_inprocess.py), run from the repository."""
    return run_cli(*args, cwd=REPO)


@pytest.mark.parametrize("args,named", BAD, ids=[" ".join(a) for a, _ in BAD])
def test_a_bad_value_is_one_line_naming_the_key(tuned_ws, args, named):
    before = snapshot(tuned_ws)
    if args[0] == "export":  # export takes no -w: its paths are the workspace's
        r = cli(args[0], tuned_ws / args[1], "--out", tuned_ws.parent / args[3], *args[4:])
    else:
        r = sefa(tuned_ws, *args)
    line = one_error_line(r, f"error: {named}", "(valid: ")
    if "max_steps" in named:
        assert "batch_size" not in line  # the key that is wrong, not a neighbour
    assert snapshot(tuned_ws) == before
    assert not (tuned_ws.parent / "exported").exists()


def test_a_bad_value_in_a_real_process_is_the_same_one_line(tuned_ws):
    """The cases above run in-process; one through the real entry point in a child, whose
    whole stderr is the line (no traceback, no warning printed while importing)."""
    before = snapshot(tuned_ws)
    r = sefa_child(tuned_ws, "train", "training.lr=nan")
    line = one_error_line(r, "error: training.lr: nan", "(valid: ")
    assert r.stderr == line + "\n"
    assert snapshot(tuned_ws) == before


def test_a_bad_value_in_sefa_yaml_names_the_file_and_key(store, tmp_path):
    ws = tmp_path / "ws"
    ws.mkdir()
    (ws / "sefa.yaml").write_text(yaml.safe_dump({"reflow": {"samples_per_window": 0}}))
    before = snapshot(ws)
    one_error_line(sefa(ws, "run"), "sefa.yaml: reflow.samples_per_window: 0 is too small")
    assert snapshot(ws) == before


# --- train --out ----------------------------------------------------------------------------------

def test_train_out_uses_the_workspace_settings_and_says_which_keys_it_sees(tuned_ws, tmp_path):
    before = snapshot(tuned_ws)
    out = tmp_path / "out"
    r = sefa_child(tuned_ws, "train", "--out", out, "shape_meta.obs_keys=[state]",
                   "shape_meta.obs.state.dims=[0,2]",
                   "training.max_steps=1", "training.batch_size=8", "training.val_every=1",
                   "training.checkpoint_every=1", "training.val_sample_windows=2",
                   "training.val_batches=1", "training.lr_warmup_steps=0")
    assert r.returncode == 0, r.stderr[-2000:]
    assert "--out trains with the settings of" in r.stderr
    assert "observations (1): state (5,)[0:2]" in r.stderr
    # obs_keys left out a key the store has, and that is said
    assert "not observed: keypoint (left out by shape_meta.obs_keys)" in r.stderr
    cfg = json.loads((out / "checkpoints/latest/config.json").read_text())["train_config"]
    assert cfg["policy"]["mlp_hidden_dims"] == [8, 8]  # sefa.yaml's, not the default network
    assert list(cfg["shape_meta"]["obs"]) == ["state"]
    assert snapshot(tuned_ws) == before  # --out keeps nothing in the workspace


# --- every numeric knob states its range ----------------------------------------------------------

def _config_classes():
    from sefa_pipelines.stages import (AlignStageConfig, DistillStageConfig, PipelineConfig,
                                  ReflowStageConfig)
    from sefa_model import config

    return [config.ObsSpec, config.ActionSpec, config.PolicyConfig, config.FlowConfig, config.DiffusionConfig,
            config.TrainingConfig, PipelineConfig, ReflowStageConfig, AlignStageConfig,
            DistillStageConfig]


def _leaves(tp) -> set:
    args = typing.get_args(tp)
    return set().union(*(_leaves(a) for a in args)) if args else {tp}


def _is_list(tp) -> bool:
    return typing.get_origin(tp) is list or any(_is_list(a) for a in typing.get_args(tp))


@pytest.mark.parametrize("cls", _config_classes(), ids=lambda c: c.__name__)
def test_every_numeric_knob_states_a_range_that_refuses_nan(cls):
    from sefa_data.config_io import from_dict
    from sefa_data.errors import ConfigError

    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        tp = hints[f.name]
        if not _leaves(tp) & {int, float}:
            continue
        valid = f.metadata.get("valid")
        assert valid is not None, f"{cls.__name__}.{f.name} states no valid range"
        values = [math.nan, math.inf] if float in _leaves(tp) else []
        values += [] if valid.lo is None else [valid.lo - 1]
        values += [] if valid.hi is None else [valid.hi + 1]
        assert values, f"{cls.__name__}.{f.name}: a range that refuses nothing"
        for value in values:
            with pytest.raises(ConfigError) as e:
                from_dict(cls, {f.name: [value] if _is_list(tp) else value})
            assert e.value.key.startswith(f.name), e.value.line()
            assert "valid: " in e.value.what


def test_save_pipeline_keeps_the_replaced_settings(tmp_path):
    from sefa_pipelines.stages import PipelineConfig, load_pipeline, save_pipeline

    (tmp_path / "sefa.yaml").write_text("reflow: {iters: 3}\n")
    save_pipeline(tmp_path, PipelineConfig())
    assert (tmp_path / "sefa.yaml.bak").read_text() == "reflow: {iters: 3}\n"
    assert load_pipeline(tmp_path).reflow.iters == 1
