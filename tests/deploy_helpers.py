"""Tiny checkpoints for the deployment tests, trained in seconds on the real Push-T low-dim data,
and a `sefa serve` process on a free loopback port.

    flow      the base rectified flow (its own solver: rk45), 10 steps
    distill   a one-step student made the way `sefa distill` makes it (reflow couplings of the
              flow, then training at t = 0 with euler-1, t_eps 0, kind sefa_one_step)
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
TINY = ["shape_meta.obs.keypoint.type=low_dim", "shape_meta.obs.state.dims=[0,2]",
        "policy.head=mlp", "policy.mlp_hidden_dims=[64,64]", "policy.time_embed_dim=32",
        "training.batch_size=64", "training.max_steps=10", "training.val_every=10",
        "training.val_sample_windows=8", "training.val_batches=1"]


def student_workspace(store_workspace: Path, ws: Path, method: str, extra: str = "") -> Path:
    """A new workspace at `ws` on `store_workspace`'s dataset.zarr whose sefa.yaml trains the
    TINY base flow, one small reflow round and a 4-step student of `method` (no alignment);
    `extra`: more of the student's train overrides, each ", 'key=value'"."""
    import shutil

    ws.mkdir()
    shutil.copytree(store_workspace / "dataset.zarr", ws / "dataset.zarr")
    (ws / "sefa.yaml").write_text(
        "train: [" + ", ".join(f"'{o}'" for o in TINY) + "]\n"
        "reflow: {iters: 1, samples_per_window: 2, max_windows: 32}\n"
        f"distill: {{method: {method}, align: false, "
        f"train_overrides: ['training.max_steps=4'{extra}]}}\n")
    return ws


def make_checkpoints(shared_data: Path, ws: Path) -> Path:
    from sefa_data.ingest import IngestOptions, ingest
    from sefa_model.config import load_train_config
    from sefa_model.policy.artifact import Policy
    from sefa_model.sefa.reflow import CouplingConfig, generate_couplings
    from sefa_model.data.couplings import PairSource
    from sefa_model.train.loop import train
    from sefa_pipelines.stages import student_config

    ingest([shared_data / "pusht_cchi_v7_replay.zarr"], ws / "dataset.zarr",
           IngestOptions(fps=10, keys=["keypoint", "state", "action"]))
    train(load_train_config(None, TINY), ws / "flow", ws / "dataset.zarr")
    flow = ws / "flow" / "checkpoints" / "latest"
    generate_couplings(Policy.load(flow), ws / "dataset.zarr", ws / "couplings.zarr",
                       CouplingConfig(samples_per_window=2, solver="euler", steps=2, max_windows=32))
    # the one-step student exactly as `sefa distill` builds it
    train(student_config(load_train_config(None, TINY), []), ws / "distill", ws / "dataset.zarr",
          init_from=flow, couplings=PairSource.couplings(ws / "couplings.zarr", "sefa_one_step"))
    return ws


# (checkpoint, solver, steps): the one-step student as it is, the base flow unrolled Euler-4
EXPORT_SETTINGS = {"one-step": ("distill", None, None), "euler-4": ("flow", "euler", 4)}


def need(fmt: str) -> None:
    """ONNX needs the `deploy` extra (scripts/setup.sh installs it); skip without it."""
    import pytest

    if fmt == "onnx":
        pytest.importorskip("onnxscript", reason="the deploy extra is not installed")
        pytest.importorskip("onnxruntime", reason="the deploy extra is not installed")


class Exports:
    """exports(name, fmt) -> an export directory of EXPORT_SETTINGS[name], made on first use
    and shared by the test files (ONNX export takes seconds)."""

    def __init__(self, ws: Path):
        self.ws, self.made = ws, {}

    def __call__(self, name: str, fmt: str) -> Path:
        from sefa_deploy.export import export_policy

        need(fmt)
        if (name, fmt) not in self.made:
            ckpt, solver, steps = EXPORT_SETTINGS[name]
            self.made[name, fmt] = self.ws / f"export_{name}_{fmt}"
            export_policy(self.ws / ckpt, self.made[name, fmt], fmt=fmt, solver=solver, steps=steps)
        return self.made[name, fmt]


def validation_windows(policy, store: Path, n: int = 100) -> dict[str, np.ndarray]:
    """`n` evenly spread validation windows: raw observations (B, To, ...) in store units."""
    from sefa_data.store.zarr_store import EpisodeStore
    from sefa_model.data.windows import PolicyData

    data = PolicyData(policy.cfg, EpisodeStore.open(store), policy.normalizer)
    sampler = data.valid or data.train
    idx = np.unique(np.linspace(0, len(sampler) - 1, n).round().astype(int))
    batch = sampler.batch(idx)
    return {k: batch[k] for k in policy.cfg.shape_meta.obs}


def sefa(*args, check: bool = True) -> subprocess.CompletedProcess:
    r = subprocess.run([sys.executable, "-m", "sefa_cli.main", *map(str, args)], cwd=REPO,
                       capture_output=True, text=True)
    if check:
        assert r.returncode == 0, r.stderr[-3000:]
    return r


class Server:
    """`sefa serve PATH --port 0 --json` as a separate process; the port it picked is read from
    its first JSON line. `fault`: the policy served with that fault (tests/serve_with_fault.py)."""

    def __init__(self, path: Path, *args: str, fault: str | None = None):
        start = ["-m", "sefa_cli.main"] if fault is None else [str(REPO / "tests" / "serve_with_fault.py")]
        env = None if fault is None else {**os.environ, "SEFA_TEST_FAULT": fault}
        self.proc = subprocess.Popen(
            [sys.executable, *start, "serve", str(path), "--host", "127.0.0.1",
             "--port", "0", "--device", "cpu", "--json",
             # a held or broken policy would hold or fail the startup timing's calls
             *([] if fault is None else ["--no-timing"]), *args],
            cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
            # background shells start jobs with SIGINT ignored; the child must see it
            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
        line = self.proc.stdout.readline()
        if not line:
            raise RuntimeError(f"server did not start: {self.proc.stderr.read()[-3000:]}")
        self.ready = json.loads(line)  # where it listens, what step requests run, its timing
        self.port = self.ready["port"]
        self.result: tuple[int, str, str] | None = None
        self.url = f"ws://127.0.0.1:{self.port}"

    def stop(self, sig: int = signal.SIGTERM, timeout: float = 20) -> tuple[int, str, str]:
        """Signal it and wait; the exit code and the whole output (once stopped, the same)."""
        if self.result is None:
            if self.proc.poll() is None:
                self.proc.send_signal(sig)
            try:
                out, err = self.proc.communicate(timeout=timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                out, err = self.proc.communicate()
                err += f"\n(killed: no exit within {timeout} s of the signal)"
            self.result = (self.proc.returncode, out, err)
        return self.result


def connect_sefa(url: str, **kwargs):
    """A bare websocket (another library than our client's) speaking sefa's protocol: it offers
    the subprotocol, as every sefa client must (without it the server speaks openpi's)."""
    from websockets.sync.client import connect

    from sefa_deploy.client import SUBPROTOCOL

    return connect(url, subprotocols=[SUBPROTOCOL], **kwargs)


def port_is_free(port: int) -> bool:
    """Nothing listens on the port and a new server could listen on it. With SO_REUSEADDR, as
    servers bind (asyncio does): the closed connections' TIME_WAIT entries do not hold it."""
    import socket

    with socket.socket() as probe:
        if probe.connect_ex(("127.0.0.1", port)) == 0:
            return False
    with socket.socket() as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(("127.0.0.1", port))
            s.listen()
        except OSError:
            return False
    return True


def wait_for(condition, timeout: float = 10.0) -> bool:
    end = time.time() + timeout
    while time.time() < end:
        if condition():
            return True
        time.sleep(0.02)
    return False


def blocked_env() -> dict:
    return {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}


def normalize_action(meta: dict, action: np.ndarray) -> np.ndarray:
    """An action in robot units -> normalized units, with an export's own metadata parameters."""
    n = meta["action_normalizer"]
    return action * np.asarray(n["scale"], np.float32) + np.asarray(n["offset"], np.float32)
