"""Living in a workspace (issue 15), through the real `sefa` command on a small Push-T store:
upstream stages are announced, old runs are kept, an interrupted training resumes, evaluations
are cached and kept, a copied workspace stays cached, a one-episode store gets a window-level
split, and long stages print progress lines when piped."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from cli_inprocess import run_cli

REPO = Path(__file__).resolve().parents[2]
TINY = ["shape_meta.obs.keypoint.type=low_dim", "shape_meta.obs.state.dims=[0,2]",
        "policy.head=mlp", "policy.mlp_hidden_dims=[32,32]", "policy.time_embed_dim=16",
        "training.max_steps=40", "training.batch_size=32", "training.lr=1e-3",
        "training.lr_warmup_steps=5", "training.val_every=20", "training.checkpoint_every=20",
        "training.val_batches=1", "training.val_sample_windows=8", "training.log_every=10"]


def sefa(ws: Path, *args, ok: bool = True) -> subprocess.CompletedProcess:
    """`sefa ARGS -w WS` in-process through sefa_cli.main.main (tests/cli_inprocess.py), with the one
    torch thread its children had; Ctrl-C, --version and -h run in real child processes."""
    r = run_cli(*args, "-w", ws, cwd=REPO, threads=1)
    if ok:
        assert r.returncode == 0, r.stderr[-3000:]
    return r


def ingest(ws: Path, source: Path) -> subprocess.CompletedProcess:
    return sefa(ws, "ingest", source, "--fps", "10", "--key", "keypoint", "--key", "state",
                "--key", "action")


def run_dirs(ws: Path, artifact: str) -> list[str]:
    return sorted(p.name for p in (ws / "runs" / artifact).iterdir() if not p.name.startswith("."))


@pytest.fixture(scope="module")
def store(shared_data, tmp_path_factory) -> Path:
    ws = tmp_path_factory.mktemp("store")
    ingest(ws, shared_data / "pusht_cchi_v7_replay.zarr")
    return ws / "dataset.zarr"


@pytest.fixture
def ws(store, tmp_path) -> Path:
    """A workspace holding a copy of the store and nothing else."""
    ws = tmp_path / "ws"
    ws.mkdir()
    shutil.copytree(store, ws / "dataset.zarr")
    return ws


def test_no_silent_upstream_run(ws):
    r = sefa(ws, "reflow", "--iters", "1", ok=False)
    lines = [line for line in r.stderr.splitlines() if line.startswith("error:")]
    assert r.returncode == 1 and len(lines) == 1, r.stderr
    assert "`sefa reflow` must first run train" in lines[0] and "--yes" in lines[0]
    assert "Traceback" not in r.stderr and not (ws / "runs").exists()  # nothing started
    # on a CPU-only machine the default head is the small one, and that is said
    assert "mlp head" in lines[0] or not _cpu_only()
    sefa(ws, "train", *TINY)
    r = sefa(ws, "reflow", "--max-windows", "16", "--samples", "2")  # upstream cached: no question
    assert "reflow iter 1: running" in r.stderr and "train: cached" in r.stderr


def _cpu_only() -> bool:
    import torch

    return not torch.cuda.is_available()


def test_old_runs_survive_and_flags_stay_out_of_sefa_yaml(ws):
    (ws / "sefa.yaml").write_text(yaml.safe_dump({"train": TINY}))
    before = (ws / "sefa.yaml").read_text()
    r = sefa(ws, "train")
    assert "train: running" in r.stderr
    first = run_dirs(ws, "train")
    kept = {p.relative_to(ws): p.read_bytes() for p in (ws / "runs/train" / first[0]).rglob("*")
            if p.is_file()}
    r = sefa(ws, "train", "training.max_steps=30")
    assert "command-line settings on top of sefa.yaml" in r.stderr
    assert (ws / "sefa.yaml").read_text() == before  # flags are not written back
    assert len(run_dirs(ws, "train")) == 2  # the new run beside the old one
    assert {p: (ws / p).read_bytes() for p in kept} == kept
    manifest = json.loads((ws / "train" / "manifest.json").read_text())
    assert manifest["flags"] == {"train": ["training.max_steps=30"]}
    assert manifest["command"].startswith("sefa train training.max_steps=30")
    assert manifest["summary"]["steps"] == 30
    # back to the first settings: the kept run becomes current again, nothing is trained
    (ws / ".sefa" / "flags.yaml").unlink()
    r = sefa(ws, "train")
    assert "train: cached" in r.stderr and "a kept run" in r.stderr
    assert os.path.realpath(ws / "train") == str((ws / "runs/train" / first[0]).resolve())
    # --save writes the command line into sefa.yaml
    sefa(ws, "train", "training.max_steps=30", "--save")
    assert "training.max_steps=30" in (ws / "sefa.yaml").read_text()
    assert not (ws / ".sefa" / "flags.yaml").exists()


def test_a_trials_settings_are_said_by_a_plain_command_and_reset_drops_them(ws):
    """A 20-step trial, then a plain `sefa train`: its cached answer is the trial's run, and the
    command says so first and last, with how to drop those settings; `sefa config reset` drops
    them, and the plain command then runs sefa.yaml's settings."""
    (ws / "sefa.yaml").write_text(yaml.safe_dump({"train": TINY}))
    r = sefa(ws, "train", "training.max_steps=20")
    assert "`sefa config reset` drops them" in r.stderr
    trial = os.path.realpath(ws / "train")
    r = sefa(ws, "train")
    lines = r.stderr.strip().splitlines()
    said = ("note: earlier command-line settings still apply on top of sefa.yaml: train "
            "training.max_steps=20 (`sefa config reset` drops them, --save writes them to "
            "sefa.yaml)")
    assert lines[0] == said and lines[-1] == said, r.stderr
    assert "train: cached" in r.stderr and os.path.realpath(ws / "train") == trial
    r = sefa(ws, "config", "reset")
    assert r.stdout.strip() == (
        "dropped the command-line settings kept on top of sefa.yaml: train training.max_steps=20 "
        "(runs made with them are kept; the same settings on a command line make their run "
        "current again)")
    assert not (ws / ".sefa/flags.yaml").exists() and Path(trial).is_dir()
    r = sefa(ws, "train")
    assert "earlier command-line settings" not in r.stderr
    assert json.loads((ws / "train/manifest.json").read_text())["summary"]["steps"] == 40
    r = sefa(ws, "config", "reset")
    assert r.stdout.strip() == "no command-line settings are kept: sefa.yaml alone applies"


def test_resume_after_sigint_continues_from_the_last_checkpoint(ws):
    settings = TINY + ["training.max_steps=1500", "training.checkpoint_every=50",
                       "training.val_every=500"]
    (ws / "sefa.yaml").write_text(yaml.safe_dump({"train": settings}))
    # Ctrl-C's default action in the child even when this test runs in a background job, whose
    # children inherit SIGINT ignored (and then Python installs no KeyboardInterrupt handler)
    proc = subprocess.Popen([sys.executable, "-m", "sefa_cli.main", "train", "-w", str(ws)], cwd=REPO,
                            env={**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"},
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.time() + 120
    while time.time() < deadline and not list(ws.glob("runs/train/.*.partial/checkpoints/latest")):
        time.sleep(0.05)
    proc.send_signal(signal.SIGINT)
    err = proc.communicate(timeout=60)[1]
    assert proc.returncode == 130, (proc.returncode, err)
    partial = list(ws.glob("runs/train/.*.partial"))
    assert len(partial) == 1 and f"interrupted: kept {partial[0].relative_to(ws).as_posix()} at step " in err
    state = json.loads((partial[0] / "checkpoints/latest/training_state/state.json").read_text())
    step = json.loads(json.dumps(state)).get("step", None)
    status = {r["stage"]: r["state"] for r in json.loads(sefa(ws, "status", "--json").stdout)["rows"]}
    assert status["train"] == "missing"  # a resumable state, not a complete artifact
    saved = json.loads((partial[0] / "checkpoints/latest/config.json").read_text())["train_config"]

    r = sefa(ws, "train", "--resume")
    assert "continuing the interrupted run" in r.stderr
    resumed_at = int(re.search(r"resuming \S+ at step (\d+)", r.stderr).group(1))
    assert 0 < resumed_at < 1500 and resumed_at % 50 == 0
    assert step is None or resumed_at == step
    manifest = json.loads((ws / "train" / "manifest.json").read_text())
    assert manifest["summary"]["steps"] == 1500
    final = json.loads((ws / "train/checkpoints/latest/config.json").read_text())["train_config"]
    assert final == saved  # the same resolved config
    logs = [json.loads(line)["step"] for line in (ws / "train/logs.jsonl").read_text().splitlines()]
    assert logs == sorted(logs) and len(logs) == len(set(logs))  # one run's log, no repeats


def test_nothing_to_resume_is_a_clear_error(ws):
    (ws / "sefa.yaml").write_text(yaml.safe_dump({"train": TINY}))
    r = sefa(ws, "train", "--resume", ok=False)
    assert r.returncode == 1 and "nothing to resume" in r.stderr and "Traceback" not in r.stderr


@pytest.fixture(scope="module")
def trained(store, tmp_path_factory) -> Path:
    ws = tmp_path_factory.mktemp("trained")
    shutil.copytree(store, ws / "dataset.zarr")
    sefa(ws, "train", *TINY)
    return ws


def test_eval_is_cached_and_kept_apart_by_settings(trained):
    args = ["eval", "--offline", "--windows", "16", "--samples", "2", "--json"]
    first = json.loads(sefa(trained, *args).stdout)
    started = time.monotonic()
    again = json.loads(sefa(trained, *args).stdout)
    assert [r.pop("cached") for r in first] == [False] and [r.pop("cached") for r in again] == [True]
    assert again == first  # read back, not recomputed
    assert time.monotonic() - started < 30
    other = json.loads(sefa(trained, "eval", "--offline", "--windows", "16", "--samples", "3",
                            "--json").stdout)
    assert other[0]["cached_in"] != first[0]["cached_in"]
    for seeds in (1, 2):
        sefa(trained, "eval", "--env", "pusht", "--n-test", seeds, "--max-steps", "16")
    logs = [json.loads(p.read_text()) for p in sorted(trained.glob("evals/pusht-*/eval_log.json"))]
    assert sorted(log["n_test"] for log in logs) == [1, 2]  # neither overwrote the other
    rows = json.loads(sefa(trained, "results", "--json").stdout)
    assert len(rows) == 4 and all(not os.path.isabs(r["folder"]) for r in rows)
    assert {r["checkpoint"] for r in rows} == {"train"}


def test_a_stage_command_builds_the_base_config_once(trained, monkeypatch):
    """The stage list, the device line and the batch check share one reading of the base
    config (it was read and checked three times per command)."""
    import sefa_pipelines.stages as stages

    built, real = [], stages.base_train_config
    monkeypatch.setattr(stages, "base_train_config", lambda *a: built.append(a) or real(*a))
    r = run_cli("train", *TINY, "-w", trained)
    assert r.returncode == 0, r.stderr
    assert "train: cached" in r.stderr and len(built) == 1


def test_a_copied_workspace_is_fully_cached(trained, tmp_path):
    sefa(trained, "reflow", "--max-windows", "16", "--samples", "2", "--yes")
    copy = tmp_path / "copy"
    shutil.copytree(trained, copy, symlinks=True)
    rows = json.loads(sefa(copy, "status", "--json").stdout)["rows"]
    states = {r["stage"]: r["state"] for r in rows}
    assert states["train"] == "cached" and states["reflow iter 1"] == "cached", rows
    for path in copy.glob("runs/**/manifest.json"):
        m = json.loads(path.read_text())  # (the recorded command line keeps its -w as typed)
        assert str(trained) not in json.dumps({k: m[k] for k in ("inputs", "config", "summary")})
    r = sefa(copy, "reflow", "--max-windows", "16", "--samples", "2")
    assert ": running" not in r.stderr


def test_one_episode_store_gets_a_window_level_split(shared_data, tmp_path):
    import zarr

    src = zarr.open_group(str(shared_data / "pusht_cchi_v7_replay.zarr"), mode="r")
    end = int(src["meta/episode_ends"][0])
    one = zarr.open_group(str(tmp_path / "one.zarr"), mode="w", zarr_format=2)
    for key in ("keypoint", "state", "action"):
        one.create_array(f"data/{key}", data=src[f"data/{key}"][:end])
    one.create_array("meta/episode_ends", data=np.array([end], dtype=np.int64))
    ws = tmp_path / "ws"
    r = ingest(ws, tmp_path / "one.zarr")
    assert "too few for an episode-level validation split" in r.stderr
    r = sefa(ws, "train", *TINY)
    assert "a window-level split instead" in r.stderr
    assert "validation at step 40/40" in r.stderr
    records = [json.loads(line) for line in (ws / "train/logs.jsonl").read_text().splitlines()]
    assert any("val_action_mse" in rec for rec in records)
    r = sefa(ws, "eval", "--offline", "--windows", "8", "--samples", "2")
    assert "a window-level split" in r.stderr and "valid (window-level) windows" in r.stdout


def test_progress_lines_in_piped_output(trained):
    """Each long stage prints plain lines with its numbers, rate and ETA when not a terminal."""
    r = sefa(trained, "train", "training.max_steps=60", "--force")
    assert re.search(r"^train 3\d/60 \(\d+%\) loss \S+ \| [\d.e+]+ (step/s|s/step) \| elapsed "
                     r"\d+:\d\d \| ETA \d+:\d\d$", r.stderr, re.M), r.stderr
    assert re.search(r"^validation at step 40/60: action MSE \S+ vs mean action \S+ \(", r.stderr, re.M)
    r = sefa(trained, "reflow", "--max-windows", "24", "--samples", "2", "--force")
    assert re.search(r"^couplings 24/24 \(100%\) couplings 48 NFE per solve \S+ \|", r.stderr, re.M)
    r = sefa(trained, "eval", "--offline", "--windows", "8", "--samples", "2", "--force")
    assert re.search(r"^offline eval \d+/1000 \(\d+%\) NFE \d+", r.stderr, re.M)
    r = sefa(trained, "eval", "--env", "pusht", "--n-test", "2", "--max-steps", "16", "--force")
    assert re.search(r"^rollouts 2/2 \(100%\) mean score [\d.]+ success \d+% \|", r.stderr, re.M)


def test_alignment_reports_quantiles_and_warns_on_a_useless_eps(trained):
    sefa(trained, "reflow", "--max-windows", "16", "--samples", "2", "--yes")
    r = sefa(trained, "align", "--eps", "1e-9")
    assert "distance quantiles: q0 " in r.stdout
    assert "warning: eps 1e-09 replaces 0.0% of the couplings" in r.stdout
    r = sefa(trained, "align", "--eps", "1e9")
    assert "replaces 100.0% of the couplings" in r.stdout
    # two eps, two kept alignment runs side by side
    assert len(run_dirs(trained, "align")) == 2


def test_version_short_help_and_config_show(trained):
    r = subprocess.run([sys.executable, "-m", "sefa_cli.main", "--version"], capture_output=True,
                       text=True, cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)})
    assert r.returncode == 0 and r.stdout.startswith("sefa ")
    r = subprocess.run([sys.executable, "-m", "sefa_cli.main", "align", "-h"], capture_output=True,
                       text=True, cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO), "COLUMNS": "200"})
    assert r.returncode == 0 and "Example: sefa align --eps" in r.stdout and "else 0.1" in r.stdout
    shown = yaml.safe_load(sefa(trained, "config", "show").stdout)
    # every key, resolved: the defaults, sefa.yaml and the command line's settings together
    assert {"max_steps", "batch_size", "lr", "num_workers", "ema_power"} <= set(shown["train"]["training"])
    assert shown["train"]["policy"]["mlp_hidden_dims"] == [32, 32]
    assert "policy.head=mlp" in shown["command_line"]["train"]
    assert {"eps", "variant", "tol"} <= set(shown["resolved"]["align"])
