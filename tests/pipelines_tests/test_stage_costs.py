"""Issue 25, traps 2 and 4, through the real `sefa` command (in-process, a small Push-T store):
every stage says what it will cost before it starts (steps and where the number comes from,
windows x K), reflow and distill training steps have flags (--train-steps) and `sefa config set` exists, the couplings
bar starts before the first block; settings that change nothing retrain nothing, and a longer
training continues the finished run."""

from __future__ import annotations

import json
import os
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

import sefa_cli.main

TINY = ["shape_meta.obs.keypoint.type=low_dim", "shape_meta.obs.state.dims=[0,2]",
        "policy.head=mlp", "policy.mlp_hidden_dims=[32,32]", "policy.time_embed_dim=16",
        "training.max_steps=20", "training.batch_size=32", "training.lr=1e-3",
        "training.lr_warmup_steps=5", "training.val_every=10", "training.checkpoint_every=10",
        "training.val_batches=1", "training.val_sample_windows=8", "training.log_every=10"]


@pytest.fixture(autouse=True)
def one_thread():
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def sefa(capsys, ws: Path, *args, ok: bool = True) -> tuple[int, str]:
    """(exit code, stderr + stdout) of one `sefa` command, run in this process."""
    argv = sys.argv
    sys.argv = ["sefa", *map(str, args), "-w", str(ws)]
    try:
        sefa_cli.main.main()
        rc = 0
    except SystemExit as e:
        rc = e.code if isinstance(e.code, int) else 1
    finally:
        sys.argv = argv
    out = capsys.readouterr()
    text = out.err + out.out
    if ok:
        assert rc == 0, text[-3000:]
    return rc, text


@pytest.fixture(scope="module")
def store(shared_data, tmp_path_factory) -> Path:
    from sefa_data.ingest import IngestOptions, ingest

    path = tmp_path_factory.mktemp("store") / "dataset.zarr"
    ingest([shared_data / "pusht_cchi_v7_replay.zarr"], path,
           IngestOptions(fps=10, keys=["keypoint", "state", "action"]), log=lambda line: None)
    return path


@pytest.fixture
def ws(store, tmp_path) -> Path:
    ws = tmp_path / "ws"
    ws.mkdir()
    shutil.copytree(store, ws / "dataset.zarr")
    return ws


def manifest(ws: Path, artifact: str) -> dict:
    return json.loads((ws / artifact / "manifest.json").read_text())


def weights(run: Path) -> dict[str, np.ndarray]:
    from safetensors.numpy import load_file

    return load_file(run / "checkpoints" / "latest" / "model.safetensors")


def test_bookkeeping_changes_retrain_nothing_and_more_steps_continue(ws, tmp_path, capsys):
    # a fixed schedule length: a longer run has the same learning rate over the steps done
    sefa(capsys, ws, "train", *TINY, "training.lr_decay_steps=100")
    first = manifest(ws, "train")

    # log, validation and checkpoint cadence change no weight: nothing reruns
    _, text = sefa(capsys, ws, "train", "training.log_every=5", "training.val_every=5",
                   "training.checkpoint_every=5", "training.num_workers=0")
    assert "train: cached" in text and "running" not in text, text
    _, text = sefa(capsys, ws, "status")
    assert "stale" not in text, text

    # a workspace whose manifest was written before these keys left the cache key (its hash
    # taken over the whole config, cadence included) stays cached
    path = Path(ws / "train" / "manifest.json")
    from sefa_pipelines.runner import config_hash

    path.write_text(json.dumps({**first, "config_hash": config_hash(first["config"])}))
    _, text = sefa(capsys, ws, "train")
    assert "train: cached" in text, text

    # more steps, the same schedule: the finished run goes on from its last checkpoint
    _, text = sefa(capsys, ws, "train", "training.max_steps=30")
    line = next(l for l in text.splitlines() if "continuing runs/train/" in l)
    assert "from step 20 to 30" in line and "same settings and learning-rate schedule" in line
    longer = manifest(ws, "train")
    assert longer["summary"]["steps"] == 30 and longer["continued_from"]["exact"] is True
    assert longer["config"]["train"]["training"]["log_every"] == 5  # recorded, not keyed
    # ... and it is the run a fresh 30-step training makes
    sefa(capsys, ws, "train", "--out", tmp_path / "fresh")
    fresh, continued = weights(tmp_path / "fresh"), weights(ws / "train")
    assert all(np.array_equal(fresh[k], continued[k]) for k in fresh)
    assert len([p for p in (ws / "runs" / "train").iterdir() if not p.name.startswith(".")]) == 2

    # the default schedule spans max_steps, so a longer one is another schedule: --resume
    # continues it anyway, and says what that means
    _, text = sefa(capsys, ws, "train", "--resume", "training.lr_decay_steps=null",
                   "training.max_steps=35")
    assert "nothing to resume" not in text
    line = next(l for l in text.splitlines() if "continuing runs/train/" in l)
    assert "(--resume)" in line and "from step 30 to 35" in line and "decayed over 100 steps" in line
    resumed = manifest(ws, "train")
    assert resumed["summary"]["steps"] == 35 and resumed["continued_from"]["exact"] is False


def test_each_stage_announces_its_cost_and_steps_have_flags(ws, capsys):
    sefa(capsys, ws, "train", *TINY)
    rc, text = sefa(capsys, ws, "config", "set", "reflow.batch_windows", "8")
    assert "sefa.yaml: reflow.batch_windows = 8 (was 256)" in text
    # a bad key or value is one line, and sefa.yaml is left as it was
    before = (ws / "sefa.yaml").read_text()
    for key, value, words in [("reflow.train_stepz", "3", "did you mean 'train_steps'"),
                              ("distill.train_steps", "0", "too small"),
                              ("distill.steps", "0", "too small"),
                              ("train.training.maxsteps", "5", "did you mean 'max_steps'")]:
        rc, text = sefa(capsys, ws, "config", "set", key, value, ok=False)
        errors = [l for l in text.splitlines() if l.startswith("error:")]
        assert rc == 1 and len(errors) == 1 and words in errors[0], text
        assert "Traceback" not in text and (ws / "sefa.yaml").read_text() == before

    # reflow's flow inherits the base flow's steps unless told: said before it starts
    _, text = sefa(capsys, ws, "reflow", "--iters", "2", "--max-windows", "16", "--samples", "2",
                   "--train-steps", "12")
    lines = text.splitlines()
    first = next(i for i, l in enumerate(lines) if l.startswith("reflow iter 1: 16 windows of "))
    assert "x K=2 = 32 couplings with rk45, 8 windows per block" in lines[first]
    # the bar from the first second: 0 done before any block, then moving inside the first
    # block with its solve (none of its couplings written yet), an ETA once one is measured
    bars = [l for l in lines[first:] if l.startswith("couplings ")]
    block = next(i for i, b in enumerate(bars) if b.startswith("couplings 8/16"))
    assert bars[0].startswith("couplings 0/16") and block > 1, bars
    assert all(" couplings 0 NFE in block " in b for b in bars[1:block]), bars
    assert "ETA" in bars[block], bars
    assert any(l.startswith("reflow iter 2: trains a reflowed flow, 12 steps (reflow.train_steps "
                            "(`sefa reflow --train-steps`)); then 16 windows") for l in lines), text
    flow = manifest(ws, "reflow/iter_2")
    assert flow["summary"]["flow"]["steps"] == 12
    assert flow["config"]["reflowed_flow"]["training"]["max_steps"] == 12  # keyed and recorded

    # distill: inherited, and said so; then --train-steps, a config change that reruns it
    _, text = sefa(capsys, ws, "distill", "--yes")
    assert any(l.startswith("distill: 20 steps (inherited from the base flow's "
                            "training.max_steps; `sefa distill --train-steps N` sets it)")
               for l in text.splitlines()), text
    _, text = sefa(capsys, ws, "distill", "--train-steps", "8")
    assert "distill: 8 steps (distill.train_steps (`sefa distill --train-steps`))" in text
    assert manifest(ws, "distill")["summary"]["steps"] == 8
    _, text = sefa(capsys, ws, "config", "set", "distill.train_steps", "8")
    assert yaml.safe_load((ws / "sefa.yaml").read_text())["distill"]["train_steps"] == 8
    _, text = sefa(capsys, ws, "config", "show")
    assert "train_steps: 8" in text


def test_a_workspace_from_before_unkeyed_keys_stays_cached_and_resumable(tmp_path, monkeypatch):
    """What an older sefa left (a manifest hashed over the whole config, cadence included, in a
    folder named after that hash; an interrupted build under that name) is cached and continued
    by this one: the upgrade retrains nothing. The runner alone, with toy stages."""
    from sefa_pipelines import runner
    from sefa_pipelines.runner import Stage, Workspace, canonical_json, config_hash, run_stage

    data = tmp_path / "data.txt"
    data.write_text("1 2 3")
    ws = Workspace(tmp_path / "ws")
    calls = []

    def stage(log_every: int, steps: int = 10) -> Stage:
        def run(tmp: Path) -> dict:
            calls.append(log_every)
            (tmp / "out.txt").write_text(str(steps))
            return {"steps": steps}
        return Stage("train", "train", {"train": {"training": {"max_steps": steps,
                                                               "log_every": log_every}}},
                     [str(data)], run, unkeyed=("train.training.log_every",))

    def legacy_id(s: Stage, inputs: dict) -> str:  # how run folders were named before
        key = canonical_json({"config_hash": config_hash(s.config), "inputs": inputs})
        return runner.hashlib.sha256(key.encode()).hexdigest()[:12]

    run_stage(ws, stage(50), log=lambda line: None)
    # rewrite it as the old code wrote it: the whole config hashed, the folder named after it
    inputs = ws.input_fingerprints(stage(50))
    new_dir = Path(os.path.realpath(ws.artifact_dir("train")))
    old_dir = new_dir.with_name(legacy_id(stage(50), inputs))
    m = json.loads((new_dir / "manifest.json").read_text())
    m["config_hash"] = config_hash(m["config"])
    (new_dir / "manifest.json").write_text(json.dumps(m))
    new_dir.rename(old_dir)
    runner._point(ws, "train", old_dir)

    assert ws.status(stage(50)).state == "cached"
    assert ws.status(stage(10)).state == "cached"  # and a cadence change reruns nothing
    ran, _ = run_stage(ws, stage(10), log=lambda line: None)
    assert not ran and calls == [50]

    # an interrupted build of more steps, under its old name, is continued, not started over
    longer = stage(50, steps=20)
    partial = ws.partial_dir("train", legacy_id(longer, inputs))
    (partial / "checkpoints" / "latest").mkdir(parents=True)
    (partial / "checkpoints" / "latest" / "config.json").write_text("{}")
    lines = []
    # a toy checkpoint: nothing to open
    monkeypatch.setattr(runner, "_check_resumable", lambda tmp, rel: None)
    run_stage(ws, longer, log=lines.append)
    assert any("continuing the interrupted run" in line for line in lines), lines
    assert not partial.exists()
