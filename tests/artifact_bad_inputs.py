"""The bad-input catalogue after the store (issue 23, acceptance point 2): damaged checkpoints,
a diverging training, a damaged interrupted run, an export whose outputs overflow, the server
(a policy that answers NaN, bad options), the workspace (its lock, its settings), bad values,
a damaged features cache, inputs that are not recordings; every case run through the real
`sefa` CLI in a child process, with its exit status, its one line and what became of the
workspace's artifacts.

Used by tests/cli_tests/test_artifact_catalogue.py (every case must end as it says) and by
benchmarks/bad_input_catalogue.py (prints the second table of docs/bad_input_catalogue.md).

The inputs: ONE tiny real workspace, built once through the CLI (`make_workspace`: Push-T
low-dim from ../shared/data ingested, then `sefa train` with a 32x32 MLP head for 10 steps,
`sefa reflow --iters 1 --max-windows 32 --samples 2`, `sefa align`, `sefa distill`), copied per
case with its links (`shutil.copytree(..., symlinks=True)`) and damaged there by the case's
`damage`: a flipped exponent bit, a tensor rewritten with safetensors' own writer, config.json
edited and its checksums rewritten with `sefa_model.policy.checkpoint.write_checksums` (as a training
that wrote it would have), a finished run turned into an interrupted one.
"""

from __future__ import annotations

import fcntl
import json
import os
import re
import shutil
import signal
import struct
import subprocess
import sys
import tempfile
import time
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared" / "data"
# the test modules whose writers and damage the cases reuse (test_lerobot, test_finite,
# test_features_cache) sit in the folders under tests/: importable from here however the cases
# are run (one test file, the benchmark), not only when pytest happened to collect them
for _folder in sorted((REPO / "tests").glob("*_tests")):
    if str(_folder) not in sys.path:
        sys.path.append(str(_folder))

# the settings of the tiny workspace: a 32x32 MLP head, 10 steps, and an Euler-4 flow, because
# rk45 on an untrained flow takes ~500 network calls per validation sample (seconds per stage)
TINY_TRAIN = ["shape_meta.obs.keypoint.type=low_dim", "shape_meta.obs.state.dims=[0,2]",
              "policy.head=mlp", "policy.mlp_hidden_dims=[32,32]", "policy.time_embed_dim=16",
              "flow.solver=euler", "flow.steps=4", "training.max_steps=10",
              "training.batch_size=32", "training.lr_warmup_steps=0", "training.val_every=10",
              "training.checkpoint_every=10", "training.val_batches=1",
              "training.val_sample_windows=8", "training.log_every=10"]
BUILD = [
    ["ingest", SHARED / "pusht_cchi_v7_replay.zarr", "--fps", "10", "--key", "keypoint",
     "--key", "state", "--key", "action"],
    ["train", *TINY_TRAIN],
    ["reflow", "--iters", "1", "--max-windows", "32", "--samples", "2"],
    ["align"],
    # --save: the settings typed so far go to sefa.yaml (and .sefa/flags.yaml away), so that a
    # case that must keep sefa.yaml has one to keep
    ["distill", "--save"],
]

# rewritten by any command that hashes a file whose mtime changed (the damaged one): a cache of
# (size, mtime) -> sha256, never a setting or an artifact
IGNORED = {".sefa/file_hashes.json"}

DISTILL = "distill/checkpoints/latest"
TRAIN = "train/checkpoints/latest"


@dataclass
class Case:
    name: str
    # checkpoints, training, .partial, export, server, workspace, values, features, messages
    klass: str
    made: str  # how the input was made
    # the command after `sefa`: $WS is the workspace copy, $OUT a path beside it, $CASE the
    # folder holding both (where a case's other inputs are made)
    args: list
    damage: Callable[[Path], None] | None = None  # edits the workspace copy ($WS) before the run
    exit: int = 1
    fragments: tuple[str, ...] = ()  # in the one line
    artifacts: str = "unchanged"  # the expected fate; see fate()
    # a finding: what this case does that it should not. The expectations above are then what
    # it does today (so the test fails when it changes either way) and the table says "NO".
    known: str = ""
    # a `sefa serve` case that is judged by a reply: the server is started, `request(url)` sends
    # one request and returns the reply's error as the line, then SIGTERM stops the server (its
    # exit status is the case's)
    request: Callable[[str], str] | None = None
    # where the command succeeds: the line shown is the first holding this (else the last)
    line_with: str = ""
    # the workspace lock held by this (the parent) process while the command runs, its pid in
    # the lock file as sefa's own holder writes it: another sefa run, as the command sees it
    hold_lock: bool = False


@dataclass
class Result:
    case: Case
    exit: int
    line: str
    stderr: str
    stdout: str
    artifacts: str
    changed: list  # the workspace paths that differ (for a failure message)
    work: Path  # the case's folder ($CASE)
    seconds: float = 0.0  # the command's wall time


# --------------------------------------------------------------------------- damage

def flip_exponent_bit(rel: str) -> Callable[[Path], None]:
    """The top exponent bit of the first value of a safetensors file (float32 0.01 becomes
    about 3e36: still finite, which only the checksum can tell)."""
    def go(ws: Path) -> None:
        path = ws / rel
        data = bytearray(path.read_bytes())
        header = struct.unpack("<Q", data[:8])[0]
        data[8 + header + 3] ^= 0x40
        path.write_bytes(bytes(data))
    return go


def flip_json_bit(rel: str) -> Callable[[Path], None]:
    """The low bit of the last digit of `"horizon": 16` (it reads 17): still valid JSON with a
    plausible value, which only the checksum can tell."""
    def go(ws: Path) -> None:
        path = ws / rel
        data = bytearray(path.read_bytes())
        at = data.index(b'"horizon": 16') + len(b'"horizon": 1')
        data[at] ^= 0x01
        path.write_bytes(bytes(data))
    return go


def _rewrite_checksums(ckpt: Path) -> None:
    from sefa_model.policy.checkpoint import write_checksums

    os.unlink(ckpt / "checksums.json")
    write_checksums(ckpt)


def delete_ema(ws: Path) -> None:
    (ws / DISTILL / "ema.safetensors").unlink()
    _rewrite_checksums(ws / DISTILL)


def edit_config(edit: Callable[[dict], None]) -> Callable[[Path], None]:
    def go(ws: Path) -> None:
        path = ws / DISTILL / "config.json"
        config = json.loads(path.read_text())
        edit(config)
        path.write_text(json.dumps(config, indent=1))
        _rewrite_checksums(ws / DISTILL)
    return go


def nan_weight_old_style(ws: Path) -> None:
    """A checkpoint as written before checksums existed, holding one NaN (safetensors' writer)."""
    from safetensors.torch import load_file, save_file

    ckpt = ws / DISTILL
    (ckpt / "checksums.json").unlink()
    weights = load_file(str(ckpt / "ema.safetensors"))
    weights[sorted(weights)[0]].view(-1)[0] = float("nan")
    save_file(weights, str(ckpt / "ema.safetensors"))


def overflowing(ws: Path) -> None:
    """Finite weights whose outputs are not (tests/sefa_model_tests/test_finite.py's damage, on the student)."""
    from test_finite import overflowing as scale_weights

    scale_weights(ws / DISTILL)


def interrupted_train(damage: Callable[[Path], None] | None) -> Callable[[Path], None]:
    """The finished `train` run turned into the interrupted run of the same settings: its folder
    renamed to runs/train/.<run id>.partial (a finished run's folder name is its run id,
    pipelines/runner.py:_finish), its manifest removed and the `train` pointer deleted, exactly
    what a Ctrl-C after the last checkpoint leaves. `damage` then edits that checkpoint."""
    def go(ws: Path) -> None:
        run = ws / os.readlink(ws / "train")
        partial = run.parent / f".{run.name}.partial"
        run.rename(partial)
        (partial / "manifest.json").unlink()
        (ws / "train").unlink()
        if damage is not None:
            damage(ws / partial.relative_to(ws))
    return go


def partial_is_a_file(ws: Path) -> None:
    run = ws / os.readlink(ws / "train")
    shutil.rmtree(run)
    (ws / "train").unlink()
    (run.parent / f".{run.name}.partial").write_bytes(b"not a run\n")


def without_distill(damage: Callable[[Path], None] | None) -> Callable[[Path], None]:
    """The distill pointer and its run removed (a workspace where distill has yet to run),
    then `damage`."""
    def go(ws: Path) -> None:
        run = ws / os.readlink(ws / "distill")
        (ws / "distill").unlink()
        shutil.rmtree(run)
        if damage is not None:
            damage(ws)
    return go


def _features_file(ws: Path) -> Path:
    (entry,) = (ws / "features").iterdir()
    return entry / "features.safetensors"


def flip_features_bit(ws: Path) -> None:
    """One bit near the end of the features tensor's data."""
    f = _features_file(ws)
    data = bytearray(f.read_bytes())
    data[-5] ^= 0x04
    f.write_bytes(bytes(data))


def rewrite_features(change: Callable[[dict], None]) -> Callable[[Path], None]:
    """A well-formed entry with other content, its sha256 in meta.json updated too, so that
    only the checks of the content can catch it."""
    def go(ws: Path) -> None:
        from test_features_cache import rewrite

        rewrite(_features_file(ws), change)
    return go


def wider(tensors: dict) -> None:
    import torch

    tensors["features"] = torch.cat([tensors["features"], tensors["features"][:, :1]], dim=1)


def one_nan(tensors: dict) -> None:
    tensors["features"][3, 1] = float("nan")


def symlink_loop(ws: Path) -> None:
    (ws.parent / "a.bag").symlink_to(ws.parent / "b.bag")
    (ws.parent / "b.bag").symlink_to(ws.parent / "a.bag")


def _flip_in(rel: str) -> Callable[[Path], None]:
    def go(partial: Path) -> None:
        flip_exponent_bit(rel)(partial)
    return go


def _n_action_steps(meta: dict) -> None:
    meta["n_action_steps"] = 16  # the model predicts 8


def infer_zeros(url: str) -> str:
    """One `infer` request with all-zero observations of the shapes the server's metadata
    names (sefa_deploy.client.PolicyClient)."""
    import numpy as np

    from sefa_deploy.client import PolicyClient, PolicyServerError

    with PolicyClient(url, timeout=60) as client:
        obs = {k: np.zeros(v["shape"], v["dtype"]) for k, v in client.metadata()["obs"].items()}
        try:
            client.request({"type": "infer", "obs": obs})
        except PolicyServerError as e:
            return f"error reply: {e}"
    return "an answer (no error)"


def _child_sefa(args: list, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "sefa_cli.main", *map(str, args)], cwd=REPO,
                          env={**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1",
                               **(env or {})}, capture_output=True, text=True, timeout=600,
                          stdin=subprocess.DEVNULL,
                          preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))


# the reflow that the block cases interrupt and run again: 4 blocks of 4 windows
BLOCKS_REFLOW = ["reflow", "--max-windows", "16", "--block-windows", "4"]


def kept_blocks(edit: Callable[[Path], None]) -> Callable[[Path], None]:
    """BLOCKS_REFLOW stopped by a Ctrl-C after its 2nd block (SEFA_FAULT=reflow.block:sigint:2,
    in a child), then `edit(the kept blocks' folder)`."""
    def go(ws: Path) -> None:
        r = _child_sefa([*BLOCKS_REFLOW, "-w", ws], {"SEFA_FAULT": "reflow.block:sigint:2"})
        assert r.returncode == 130, r.stderr[-2000:]
        (partial,) = ws.glob("runs/reflow/iter_1/.*.partial")
        edit(partial / "couplings.blocks")
    return go


def _truncate_block(size: int) -> Callable[[Path], None]:
    def go(blocks: Path) -> None:
        with open(blocks / "block_000000004.npz", "r+b") as f:
            f.truncate(size)
    return go


def _swap_block(blocks: Path) -> None:
    shutil.copyfile(blocks / "block_000000000.npz", blocks / "block_000000004.npz")


def edited_export(change: Callable[[dict], None], checksums: bool = True
                  ) -> Callable[[Path], None]:
    """The student exported (TorchScript) to $CASE/export, its metadata.json edited with json;
    without `checksums`, checksums.json removed (an export written before them)."""
    def go(ws: Path) -> None:
        from sefa_deploy.export import export_policy

        out = ws.parent / "export"
        export_policy(ws / DISTILL, out, fmt="torchscript")
        meta = json.loads((out / "metadata.json").read_text())
        change(meta)
        (out / "metadata.json").write_text(json.dumps(meta, indent=2))
        if not checksums:
            (out / "checksums.json").unlink()
    return go


def image_workspace(ws: Path) -> None:
    """$CASE/iws: a workspace on the first three Push-T episodes with their camera
    (tests/conftest.py:pusht_image_store), made in a child: the cases' damage runs in threads,
    and two ingests in one process at once are not what sefa does."""
    iws = ws.parent / "iws"
    iws.mkdir()
    code = ("import sys; from pathlib import Path; from conftest import pusht_image_store; "
            "pusht_image_store(Path(sys.argv[1]), Path(sys.argv[2]))")
    subprocess.run([sys.executable, "-c", code, str(SHARED), str(ws.parent / "img")], check=True,
                   cwd=REPO / "tests", env={**os.environ, "PYTHONPATH": f"{REPO}:{REPO / 'tests'}"},
                   capture_output=True, timeout=600)
    (iws / "dataset.zarr").symlink_to(ws.parent / "img" / "store.zarr")


# --------------------------------------------------------------------------- cases

_CHECKSUM = ("checksum mismatch (the file changed after it was written): the checkpoint is "
             "damaged",)
# the interrupted run's folder replaced by the finished run of the same id, pointed at
_REBUILT = "written: runs/train/.<run>.partial (removed), runs/train/<run> (new), train (new)"
_EVAL = ["eval", "$WS/distill", "--offline", "-w", "$WS"]
# a reflow that finished the interrupted run of the same settings
_REFLOWED = ("written: reflow/iter_1 (changed), runs/reflow/iter_1/.<run>.partial (removed), "
             "runs/reflow/iter_1/<run> (new)")
# TorchScript: the checks come before the format, and it needs no optional extra
_EXPORT = ["export", "$WS/distill", "--out", "$OUT", "--format", "torchscript"]
_SERVE = ["serve", "$WS/distill", "--port", "0"]

CASES = [
    # ---- checkpoints: every reader checks what it reads
    Case("a flipped exponent bit in the student's ema.safetensors, offline eval", "checkpoints",
         "bit flip", _EVAL, flip_exponent_bit(f"{DISTILL}/ema.safetensors"),
         fragments=(f"{DISTILL}/ema.safetensors: ", *_CHECKSUM)),
    Case("the same, export", "checkpoints", "bit flip", _EXPORT,
         flip_exponent_bit(f"{DISTILL}/ema.safetensors"),
         fragments=(f"{DISTILL}/ema.safetensors: ", *_CHECKSUM)),
    Case("the same, serve (stops at start-up)", "checkpoints", "bit flip", _SERVE,
         flip_exponent_bit(f"{DISTILL}/ema.safetensors"),
         fragments=(f"{DISTILL}/ema.safetensors: ", *_CHECKSUM)),
    # by design (sefa_model/policy/checkpoint.py:open_policy): a policy to run reads and hashes its
    # EMA weights only, so damaged raw weights are never deployed, and are not reported either
    Case("a flipped exponent bit in the student's raw weights (model.safetensors), export: "
         "only the EMA weights are read, checked and exported", "checkpoints", "bit flip",
         _EXPORT, flip_exponent_bit(f"{DISTILL}/model.safetensors"), exit=0,
         fragments=("wrote ", "policy.pt"), artifacts="$OUT written, workspace unchanged"),
    Case("the same, export --raw-weights (the raw weights asked for)", "checkpoints", "bit flip",
         [*_EXPORT, "--raw-weights"], flip_exponent_bit(f"{DISTILL}/model.safetensors"),
         fragments=(f"{DISTILL}/model.safetensors: ", *_CHECKSUM)),
    Case("a flipped exponent bit in the student's normalizer.safetensors, serve", "checkpoints",
         "bit flip", _SERVE, flip_exponent_bit(f"{DISTILL}/normalizer.safetensors"),
         fragments=(f"{DISTILL}/normalizer.safetensors: ", *_CHECKSUM)),
    Case("a flipped bit in the student's config.json (horizon 16 reads 17), offline eval",
         "checkpoints", "bit flip", _EVAL, flip_json_bit(f"{DISTILL}/config.json"),
         fragments=(f"{DISTILL}/config.json: ", *_CHECKSUM)),
    # with reflow --iters 1 the student starts from the base flow's EMA weights (there is no
    # reflowed flow in reflow/iter_1), so that is the upstream file distill reads; it does not
    # read the base's raw weights or optimizer state (a lean copy of a base is distilled alike)
    Case("a flipped exponent bit in the base flow's ema.safetensors, distill --force",
         "checkpoints", "bit flip", ["distill", "--force", "-w", "$WS"],
         flip_exponent_bit(f"{TRAIN}/ema.safetensors"),
         fragments=(f"{TRAIN}/ema.safetensors: ", *_CHECKSUM)),
    Case("a flipped exponent bit in the base flow's ema.safetensors, reflow --force",
         "checkpoints", "bit flip", ["reflow", "--force", "-w", "$WS"],
         flip_exponent_bit(f"{TRAIN}/ema.safetensors"),
         fragments=(f"{TRAIN}/ema.safetensors: ", *_CHECKSUM)),
    Case("the student's ema.safetensors deleted, export", "checkpoints",
         "deleted, checksums rewritten", _EXPORT, delete_ema,
         fragments=(f"{DISTILL}/ema.safetensors: missing checkpoint file: the run kept EMA "
                    "weights",)),
    Case("config.json: kind banana, offline eval", "checkpoints", "JSON edit, checksums rewritten",
         _EVAL, edit_config(lambda c: c.update(kind="banana")),
         fragments=(f"{DISTILL}/config.json", "kind: unknown kind 'banana'")),
    Case("config.json: checkpoint_format 99, serve", "checkpoints",
         "JSON edit, checksums rewritten", _SERVE,
         edit_config(lambda c: c.update(checkpoint_format=99)),
         fragments=(f"{DISTILL}/config.json",
                    "checkpoint_format: checkpoint_format 99 is not one")),
    Case("config.json: train_config without policy, export", "checkpoints",
         "JSON edit, checksums rewritten", _EXPORT,
         edit_config(lambda c: c["train_config"].pop("policy")),
         fragments=(f"{DISTILL}/config.json", "train_config.policy: train_config lacks 'policy'")),
    Case("a NaN weight in a checkpoint without checksums (as written before them), offline eval",
         "checkpoints", "safetensors save_file, checksums.json removed", _EVAL,
         nan_weight_old_style,
         fragments=(f"{DISTILL}/ema.safetensors: non-finite weights",)),
    # ---- training
    # log_every=1: the loss is read (and found NaN) at step 2 rather than at step 10
    Case("a diverging training (training.lr=1e8)", "training", "the workspace as built",
         ["train", "training.lr=1e8", "training.log_every=1", "-w", "$WS"],
         fragments=("training diverged at step 2 of 10: the training loss is nan",
                    "nothing from this run is published", "training.lr"),
         artifacts="nothing published (.sefa/flags.yaml changed)"),
    # ---- an interrupted run
    Case("an interrupted training whose checkpoint has a flipped bit, the same command",
         ".partial", "finished run renamed to .partial, bit flip",
         ["train", "-w", "$WS"],
         interrupted_train(_flip_in("checkpoints/latest/model.safetensors")),
         fragments=("the interrupted run here cannot be continued", "model.safetensors: "
                    "checksum mismatch", "pass --force to start it over")),
    Case("the same with --force (starts over)", ".partial",
         "finished run renamed to .partial, bit flip", ["train", "--force", "-w", "$WS"],
         interrupted_train(_flip_in("checkpoints/latest/model.safetensors")),
         exit=0, fragments=("train: done in",),
         artifacts=_REBUILT),
    Case("a .partial that is a file, the same command", ".partial", "a file written there",
         ["train", "-w", "$WS"], partial_is_a_file, exit=0,
         fragments=("train: removed .", ".partial left by an interrupted run"),
         line_with="left by an interrupted run", artifacts=_REBUILT),
    # ---- export
    Case("finite weights whose outputs overflow, export", "export",
         "safetensors save_file (weights x 1e30), checksums rewritten", _EXPORT, overflowing,
         fragments=("the exported policy outputs NaN or Inf on a window of",
                    "nothing is published")),
    Case("finite weights whose outputs overflow, served: one `infer` request (all-zero "
         "observations), then SIGTERM", "server",
         "safetensors save_file (weights x 1e30), checksums rewritten",
         ["serve", "$WS/distill", "--host", "127.0.0.1", "--port", "0", "--json"], overflowing,
         exit=0, fragments=("error reply: the policy produced non-finite actions (NaN or Inf in "
                            "'action'); nothing sent",), request=infer_zeros),
    # ---- workspace
    Case("a command refused by the workspace lock (another sefa run holds it)", "workspace",
         "flock on .sefa/lock by the catalogue, its pid written there",
         ["train", "training.max_steps=30", "-w", "$WS"],
         fragments=(".sefa/lock: another sefa run holds the workspace lock (pid ",),
         hold_lock=True),
    Case("the same with --save (sefa.yaml must not be rewritten)", "workspace",
         "flock on .sefa/lock by the catalogue, its pid written there",
         ["align", "--eps", "0.2", "--save", "-w", "$WS"],
         fragments=(".sefa/lock: another sefa run holds the workspace lock (pid ",),
         hold_lock=True),
    Case("a pipeline file that does not exist: sefa run nope.yaml", "workspace",
         "the workspace as built (its sefa.yaml written by --save)",
         ["run", "nope.yaml", "-w", "$WS"],
         fragments=("nope.yaml", "no such pipeline file")),
    Case("train --out: the workspace's settings, nothing kept in the workspace", "workspace",
         "the workspace as built", ["train", "--out", "$OUT", "-w", "$WS"], exit=0,
         fragments=("--out trains with the settings of",), line_with="--out trains with",
         artifacts="$OUT written, workspace unchanged"),
    # ---- server: options checked before anything is loaded
    *[Case(f"serve {opt} {value}", "server", "the workspace as built",
           ["serve", "$WS/distill", *(["--port", "0"] if opt != "--port" else []), opt, value],
           fragments=(f"error: {opt}: {value} {expect}",))
      for opt, value, expect in [
          ("--port", "99999", "is too large (valid: an integer in [0, 65535])"),
          ("--steps", "0", "is too small (valid: an integer in [1, "),
          ("--max-message-mb", "nan", "is not a finite number (valid: a finite number > 0)"),
          ("--max-queue", "-1", "is too small (valid: an integer >= 0)"),
          ("--request-timeout", "0", "is too small (valid: a finite number > 0)")]],
    # ---- values: checked before any work, one line naming the key as typed
    *[Case(" ".join(a), "values", "the workspace as built", [*a, "-w", "$WS"] if a[0] != "export"
           else a, fragments=(f"error: {named}", "(valid: "))
      for a, named in [
          (["align", "--eps", "nan"], "--eps: nan is not a finite number"),
          (["align", "--eps", "inf"], "--eps: inf is not a finite number"),
          (["train", "training.lr=nan"], "training.lr: nan"),
          (["train", "training.ema_power=nan"], "training.ema_power: nan"),
          (["train", "training.val_every=0"], "training.val_every: 0 is too small"),
          (["train", "training.max_steps=0"], "training.max_steps: 0 is too small"),
          (["train", "training.batch_size=100000000"],
           "training.batch_size: 100000000 is more than"),
          (["reflow", "--samples", "0"], "--samples: 0 is too small"),
          (["reflow", "--iters", "0"], "--iters: 0 is too small"),
          (["reflow", "--iters", "-1"], "--iters: -1 is too small"),
          (["reflow", "--max-windows", "0"], "--max-windows: 0 is too small"),
          (["reflow", "--max-windows", "-1"], "--max-windows: -1 is too small"),
          (["eval", "--offline", "--windows", "0"], "--windows: 0 is too small"),
          (["eval", "--offline", "--samples", "0"], "--samples: 0 is too small"),
          (["eval", "--offline", "--steps", "0"], "--steps: 0 is too small"),
          (["eval", "--offline", "--steps", "-1"], "--steps: -1 is too small"),
          (["eval", "--env", "pusht", "--n-test", "0"], "--n-test: 0 is too small"),
          (["eval", "--env", "pusht", "--n-test", "-1"], "--n-test: -1 is too small"),
          (["export", "$WS/distill", "--out", "$OUT", "--steps", "0"], "--steps: 0 is too small"),
          (["export", "$WS/distill", "--out", "$OUT", "--fps", "nan"],
           "--fps: nan is not a finite"),
      ]],
    # ---- the frozen-features cache distill reads: checked before it is used
    *[Case(f"the frozen-features entry: {what}, distill (its run removed)", "features", made,
           ["distill", "-w", "$WS"], without_distill(damage),
           fragments=("features/", "features.safetensors: damaged features cache entry, not used: ",
                      said, "--force"))
      for what, made, damage, said in [
          ("a flipped bit", "bit flip", flip_features_bit, "its sha256 differs"),
          ("no features tensor", "safetensors save_file, meta.json's sha256 rewritten",
           rewrite_features(lambda t: t.pop("features")), "no 'features' tensor"),
          ("one column too many", "safetensors save_file, meta.json's sha256 rewritten",
           rewrite_features(wider), "expected torch.float32 (32, "),
          ("a NaN", "safetensors save_file, meta.json's sha256 rewritten",
           rewrite_features(one_nan), "hold NaN or inf in 1 of 32 windows")]],
    Case("the NaN entry, distill --force (encodes it again)", "features",
         "safetensors save_file, meta.json's sha256 rewritten", ["distill", "--force", "-w", "$WS"],
         without_distill(rewrite_features(one_nan)), exit=0,
         fragments=("frozen features: ", "damaged (", "encoding again (--force)"),
         line_with="frozen features: ",
         artifacts="written: distill (new), features/<key> (changed), runs/distill/<run> (new)"),
    # ---- messages: inputs that are not recordings, said for what they are; -w honoured
    *[Case(f"sefa ingest of {what} into the workspace", "messages", made,
           ["ingest", path, "-w", "$WS"], mk, fragments=(said,))
      for what, made, path, mk, said in [
          ("a FIFO", "os.mkfifo", "$CASE/pipe.hdf5", lambda ws: os.mkfifo(ws.parent / "pipe.hdf5"),
           "not a regular file but a FIFO (named pipe)"),
          ("/dev/null", "none: /dev/null itself", "/dev/null", None,
           "not a regular file but a character device"),
          ("a symlink loop", "two links naming each other", "$CASE/a.bag", symlink_loop,
           "a symlink loop")]],
    Case("export distill --out $OUT -w $WS from another directory: the workspace's checkpoint",
         "messages", "the workspace as built",
         ["export", "distill", "--out", "$OUT", "--format", "torchscript", "-w", "$WS"], exit=0,
         fragments=("wrote ", "policy.pt"),
         artifacts="$OUT written, the export recorded in .sefa/exports"),
    Case("eval distill -w $WS with no distill artifact: named where it was looked for",
         "messages", "the distill pointer and run removed",
         ["eval", "distill", "--offline", "-w", "$WS"],
         without_distill(None), fragments=("$WS/distill: no such checkpoint",)),
    # ---- kept reflow blocks: verified before reuse, a damaged one solved again (issue 47)
    *[Case(f"a kept block of couplings {what}, the same reflow (once: {once})", "blocks",
           f"reflow stopped after 2 of 4 blocks (SEFA_FAULT=reflow.block:sigint:2), {made}",
           [*BLOCKS_REFLOW, "-w", "$WS"], kept_blocks(edit), exit=0,
           fragments=("couplings.blocks/block_000000004.npz: a damaged block of couplings, not "
                      f"reused ({said}", "solving it again"),
           line_with="a damaged block of couplings", artifacts=_REFLOWED)
      for what, once, made, edit, said in [
          ("truncated", "unexpected BadZipFile ... a bug in sefa", "truncate to 2000 bytes",
           _truncate_block(2000), "not a whole .npz file (BadZipFile"),
          ("emptied", "'interrupted', exit 130", "truncate to 0 bytes", _truncate_block(0),
           "not a whole .npz file (EOFError"),
          ("replaced by another block's file", "reused silently: duplicated noise",
           "block 0's file copied over block 4's", _swap_block, "it holds windows ")]],
    # ---- an edited export: refused at load, never served to fail every request (issue 47)
    Case("an export's metadata.json edited (n_action_steps 8 -> 16), serve", "export",
         "export_policy (TorchScript), metadata.json edited with json",
         ["serve", "$CASE/export", "--port", "0"], edited_export(_n_action_steps),
         fragments=("export/metadata.json: checksum mismatch (the file changed after it was "
                    "written): the export is damaged",)),
    Case("the same in an export without checksums.json (written before them), serve", "export",
         "export_policy (TorchScript), checksums.json removed, metadata.json edited with json",
         ["serve", "$CASE/export", "--port", "0"],
         edited_export(_n_action_steps, checksums=False),
         fragments=("export/metadata.json: n_action_steps 16 and action_dim 2 make "
                    "outputs.action.shape [16, 2], but it is [8, 2]: the file was edited",)),
    # ---- new options that accepted what cannot work, or blamed another setting (issue 47)
    Case("eval --key-map state=state --key-map agent_pos=state: two sources for one key (once: "
         "the last one silently won)", "options", "the workspace as built",
         ["eval", "--env", "pusht", "--key-map", "state=state", "--key-map", "agent_pos=state",
          "-w", "$WS"],
         fragments=("--key-map: 'agent_pos=state': the policy's 'state' is already fed by "
                    "'state=state'",)),
    Case("eval --key-map keypoint=nope (once: the line did not name nope)", "options",
         "the workspace as built",
         ["eval", "--env", "pusht", "--key-map", "keypoint=nope", "-w", "$WS"],
         fragments=("--key-map: 'keypoint=nope': the policy has no observation 'nope' (it "
                    "takes: keypoint, state)",)),
    Case("train shape_meta.obs.state.resize=[4,4] on a low-dim key (once: accepted, ignored)",
         "options", "the workspace as built",
         ["train", "shape_meta.obs.state.resize=[4,4]", "-w", "$WS"],
         fragments=("shape_meta.obs.state.resize: resize sets a camera's model size, and "
                    "'state' is read as low_dim",)),
    Case("train img resize [48,48] with policy.crop_shape=[84,84] (once: unexpected ValueError)",
         "options", "3 Push-T episodes with their camera (zarr), ingested at $CASE/iws",
         ["train", "shape_meta.obs.img.type=rgb", "shape_meta.obs.img.resize=[48,48]",
          "policy.crop_shape=[84,84]", "-w", "$CASE/iws"], image_workspace,
         fragments=("policy.crop_shape: [84, 84] does not fit camera 'img', whose frames the "
                    "model sees at 48x48",)),
    Case("train img resize [65536,65536] (once: blamed training.batch_size, valid [1, 1])",
         "options", "3 Push-T episodes with their camera (zarr), ingested at $CASE/iws",
         ["train", "shape_meta.obs.img.type=rgb", "shape_meta.obs.img.resize=[65536,65536]",
          "training.batch_size=8", "-w", "$CASE/iws"], image_workspace,
         fragments=("shape_meta.obs.img.resize: one training sample with camera 'img' at "
                    "65536x65536 needs at least ",)),
    Case("distill --method nope (once: named .sefa/flags.yaml, which did not exist, and listed "
         "flow, ddpm, reflow)", "options", "the workspace as built",
         ["distill", "--method", "nope", "-w", "$WS"],
         fragments=("error: --method: unknown method 'nope' (students, nearest first: ",)),
    Case("distill --method flow (a method, not a student)", "options", "the workspace as built",
         ["distill", "--method", "flow", "-w", "$WS"],
         fragments=("error: --method: 'flow' is not a student (students, nearest first: ",)),
    Case("train method=reference flow.solver=rk45 (once: blamed --solver, not given, and trained "
         "before refusing)", "options", "the workspace as built",
         ["train", "method=reference", "flow.solver=rk45", "-w", "$WS"],
         fragments=("error: method: method 'reference' is a student: `sefa distill --method "
                    "reference` trains it from the base flow",)),
]


# --------------------------------------------------------------------------- running

def _child(args: list, timeout: float = 300) -> subprocess.CompletedProcess:
    # one torch thread per child: the catalogue runs children side by side on two cores
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    env.pop("SEFA_FAULT", None)
    return subprocess.run([sys.executable, "-m", "sefa_cli.main", *map(str, args)], cwd=REPO,
                          env=env, capture_output=True, text=True, timeout=timeout,
                          stdin=subprocess.DEVNULL)


def _serve_and_request(args: list, request: Callable[[str], str]) -> subprocess.CompletedProcess:
    """The server's stderr with the reply's line appended (the line run_case reads)."""
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "sefa_cli.main", *args], cwd=REPO, env=env,
                            stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        first = proc.stdout.readline()
        line = request(json.loads(first)["serving"]) if first else ""
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            out, err = proc.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()
            out, err = proc.communicate()
    return subprocess.CompletedProcess(args, proc.returncode, first + out,
                                       err + ("\n" + line if line else ""))


@contextmanager
def _held(lock: Path) -> Iterator[None]:
    fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        os.ftruncate(fd, 0)
        os.pwrite(fd, str(os.getpid()).encode(), 0)
        yield
    finally:
        os.ftruncate(fd, 0)  # as sefa leaves it when it lets go
        os.close(fd)


def make_workspace(root: Path) -> Path:
    """The tiny workspace every case copies (module docstring); about 30 s on two cores. Built
    in-process through sefa_cli.main.main (tests/cli_inprocess.py: the same commands without five
    children's imports); the cases themselves run in children."""
    from cli_inprocess import run_cli

    ws = root / "ws"
    for args in BUILD:
        r = run_cli(*args, "-w", ws, cwd=REPO, threads=1)
        if r.returncode != 0:
            raise RuntimeError(f"building the workspace: sefa {args[0]}: {r.stderr[-2000:]}")
    return ws


def snapshot(root: Path) -> dict[str, bytes]:
    """Every file's bytes, every link's target, every folder, by relative path (links are
    recorded, not followed: a stage's pointer moving is a change)."""
    out: dict[str, bytes] = {}
    if not root.exists() and not root.is_symlink():
        return out
    if root.is_file() or root.is_symlink():
        return {".": b"-> " + os.readlink(root).encode() if root.is_symlink()
                else root.read_bytes()}
    for d, dirs, files in os.walk(root, followlinks=False):
        for name in dirs + files:
            p = Path(d) / name
            rel = p.relative_to(root).as_posix()
            if p.is_symlink():
                out[rel] = b"-> " + os.readlink(p).encode()
            elif p.is_dir():
                out[rel] = b"<dir>"
            else:
                out[rel] = p.read_bytes()
    return out


def fate(before: dict, after: dict, out_made: bool) -> tuple[str, list]:
    """unchanged: the workspace byte-identical (but for IGNORED) and no --out; nothing
    published (...): only files under .sefa/ changed (named), no artifact, run or .partial
    appeared, moved or changed, no --out; written: ...: anything else (cases meant to write),
    with what was written."""
    changed = sorted(k for k in before.keys() | after.keys()
                     if before.get(k) != after.get(k) and k not in IGNORED)
    if out_made:
        if changed and all(k.startswith(".sefa/exports") for k in changed):
            # an export of a workspace's checkpoint is recorded there (`sefa status`: stale exports)
            return "$OUT written, the export recorded in .sefa/exports", changed + ["$OUT"]
        return ("$OUT written, workspace unchanged" if not changed else "written"), \
            changed + ["$OUT"]
    if not changed:
        return "unchanged", changed
    new_empty = [k for k in changed if k not in before and after[k] == b"<dir>"
                 and not any(o.startswith(k + "/") for o in after)]
    if changed == new_empty:
        return f"unchanged but for a new empty folder {', '.join(new_empty)}/", changed
    if all(k.startswith(".sefa/") for k in changed):
        return f"nothing published ({', '.join(changed)} changed)", changed
    return "written: " + ", ".join(_what_was_written(before, after, changed)), changed


_RUN = re.compile(r"^\.?[0-9a-f]{12}(\.partial)?$")


def _what_was_written(before: dict, after: dict, changed: list) -> list[str]:
    """The changed paths as the things a reader knows: a run folder (runs/<artifact>/<run>), a
    pointer, a features entry, a file; each new, removed or changed; run ids and keys as
    <run>, <key> (they follow from the settings and the data)."""
    roots: dict[str, None] = {}
    for k in changed:
        parts = k.split("/")
        run = next((i for i, p in enumerate(parts) if parts[0] == "runs" and _RUN.match(p)), None)
        if run is not None:
            root = "/".join(parts[:run + 1])
        elif parts[0] in ("features", "evals"):
            root = "/".join(parts[:2])
        else:
            root = next(("/".join(parts[:i + 1]) for i in range(len(parts))
                         if (before.get("/".join(parts[:i + 1])) or after.get(
                             "/".join(parts[:i + 1])) or b"").startswith(b"-> ")), k)
        roots[root] = None
    out = []
    for root in roots:
        state = "new" if root not in before else "removed" if root not in after else "changed"
        name = re.sub(r"[0-9a-f]{16}", "<key>", re.sub(r"(?<![0-9a-f])[0-9a-f]{12}(?![0-9a-f])",
                                                       "<run>", root))
        out.append(f"{name} ({state})")
    return sorted(out)


def _subst(args: list, work: Path) -> list[str]:
    return [str(a).replace("$WS", str(work / "ws")).replace("$OUT", str(work / "out"))
            .replace("$CASE", str(work)) for a in args]


def run_case(case: Case, template: Path, work: Path) -> Result:
    work.mkdir(parents=True, exist_ok=True)
    ws, out = work / "ws", work / "out"
    shutil.copytree(template, ws, symlinks=True)
    if case.damage is not None:
        case.damage(ws)
    with _held(ws / ".sefa" / "lock") if case.hold_lock else nullcontext():
        before = snapshot(ws)
        args = _subst(case.args, work)
        started = time.monotonic()
        r = _serve_and_request(args, case.request) if case.request else _child(args)
        seconds = time.monotonic() - started
        after = snapshot(ws)
    artifacts, changed = fate(before, after,
                              out.exists() or out.is_symlink() or any(work.glob(".out*")))
    lines = [ln for ln in r.stderr.strip().splitlines() if ln.strip()]
    error = [ln for ln in lines if ln.startswith("error: ")]
    out_lines = [ln for ln in r.stdout.splitlines() if ln.strip()]
    # the line that matters: the error, else the one the case names, else the last report
    # line (a rebuild's "done in")
    chosen = [ln for ln in lines if case.line_with and case.line_with in ln]
    line = error[-1] if error else chosen[0] if chosen else lines[-1] if lines \
        else out_lines[-1] if out_lines else ""
    return Result(case, r.returncode, line, r.stderr, r.stdout, artifacts, changed, work,
                  seconds)


def problems(r: Result) -> list[str]:
    """What is wrong with a case's result (empty: as the catalogue says)."""
    c, found = r.case, []
    if r.exit != c.exit:
        found.append(f"exit {r.exit}, expected {c.exit}")
    if "Traceback" in r.stderr or "Traceback" in r.stdout:
        found.append("a traceback")
    errors = [ln for ln in r.stderr.splitlines() if ln.startswith("error: ")]
    if c.exit != 0 and len(errors) != 1:
        found.append(f"{len(errors)} `error:` lines, expected one")
    if c.exit == 0 and errors:
        found.append("an `error:` line in a case meant to succeed")
    missing = [f for f in c.fragments if _subst([f], r.work)[0] not in r.line]
    if missing:
        found.append(f"the line lacks {missing}")
    if r.artifacts != c.artifacts:
        found.append(f"artifacts {r.artifacts}, expected {c.artifacts} (changed: {r.changed[:8]})")
    return found


def all_cases() -> list[Case]:
    return list(CASES)


def have_shared() -> bool:
    return (SHARED / "pusht_cchi_v7_replay.zarr").is_dir()


def make_inputs(root: Path | None = None) -> Path:
    return make_workspace(Path(root or tempfile.mkdtemp(prefix="sefa-artifacts-")))


__all__ = ["CASES", "Case", "Result", "all_cases", "fate", "have_shared", "make_inputs",
           "make_workspace", "problems", "run_case", "snapshot"]
