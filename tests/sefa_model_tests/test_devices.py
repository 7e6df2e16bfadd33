"""Devices and torchrun on the CPU: every stage takes --device; torchrun with the gloo
backend gives the same couplings, manifests and rollouts as one process.

The multi-process tests launch PyTorch's own launcher (`python -m torch.distributed.run`, i.e.
torchrun) with 2 CPU processes on a loopback rendezvous."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from sefa_data.errors import SefaInputError
from sefa_model.distributed import DistContext, cpu_noise, resolve_device
from sefa_model.sefa.reflow import window_noise

REPO = Path(__file__).resolve().parents[2]
TINY = ["shape_meta.obs.keypoint.type=low_dim", "shape_meta.obs.state.dims=[0,2]",
        "policy.head=mlp", "policy.mlp_hidden_dims=[64,64]", "policy.time_embed_dim=32",
        "training.max_steps=20", "training.batch_size=64", "training.lr=1e-3",
        "training.lr_warmup_steps=5", "training.val_every=20", "training.checkpoint_every=20",
        "training.log_every=10", "training.val_batches=1", "training.val_sample_windows=8"]
# the same float arithmetic in every process: torchrun gives each worker one thread
ONE_THREAD = {**os.environ, "OMP_NUM_THREADS": "1"}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def sefa(ws: Path, *args, nproc: int = 1, check: bool = True) -> subprocess.CompletedProcess:
    launcher = ([] if nproc == 1 else
                ["-m", "torch.distributed.run", "--nproc_per_node", str(nproc),
                 "--master_addr", "127.0.0.1", "--master_port", str(free_port())])
    cmd = [sys.executable, *launcher, "-m", "sefa_cli.main", *map(str, args), "-w", str(ws)]
    r = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO, env=ONE_THREAD, timeout=600)
    if check:
        assert r.returncode == 0, r.stderr[-3000:]
    return r


def ran(r: subprocess.CompletedProcess) -> list[str]:
    return [line.split(":")[0] for line in r.stderr.splitlines() if ": running (" in line]


def manifest(ws: Path, artifact: str) -> dict:
    return json.loads((ws / artifact / "manifest.json").read_text())


@pytest.fixture(scope="module")
def store(shared_data, tmp_path_factory) -> Path:
    ws = tmp_path_factory.mktemp("store")
    sefa(ws, "ingest", shared_data / "pusht_cchi_v7_replay.zarr", "--fps", "10",
         "--key", "keypoint", "--key", "state", "--key", "action")
    return ws / "dataset.zarr"


def workspace_with(store: Path, path: Path) -> Path:
    path.mkdir()
    (path / "dataset.zarr").symlink_to(store)
    return path


@pytest.fixture(scope="module")
def ddp_workspace(store, tmp_path_factory) -> Path:
    """The base flow trained by 2 torchrun processes through the stage runner."""
    ws = workspace_with(store, tmp_path_factory.mktemp("ddp") / "ws")
    r = sefa(ws, "train", *TINY, "--device", "cpu", nproc=2)
    assert ran(r) == ["train"] and "(32 per process x 2)" in r.stderr
    return ws


# ---------------------------------------------------------------------------- devices


def test_device_names_resolve_or_fail_in_one_line():
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device("auto").type in ("cpu", "cuda", "mps")
    with pytest.raises(SefaInputError, match="unknown device 'tpu'"):
        resolve_device("tpu")
    if not torch.cuda.is_available():
        with pytest.raises(SefaInputError, match="CUDA is not available"):
            resolve_device("cuda:1")


def test_cpu_generator_noise_is_the_same_whatever_the_target_device():
    a = cpu_noise((3, 4), torch.Generator().manual_seed(5), torch.device("cpu"))
    b = torch.randn(3, 4, generator=torch.Generator().manual_seed(5))
    assert torch.equal(a, b)
    if torch.cuda.is_available():
        c = cpu_noise((3, 4), torch.Generator().manual_seed(5), torch.device("cuda"))
        assert torch.equal(c.cpu(), b)


def test_window_noise_depends_on_seed_round_and_window_only():
    w = np.array([3, 7, 11])
    full = window_noise(0, 1, w, 2, (16, 2))
    # a window's rows are the same alone, in another block or in another order
    assert torch.equal(window_noise(0, 1, np.array([7]), 2, (16, 2)), full[2:4])
    assert torch.equal(window_noise(0, 1, w[::-1], 2, (16, 2))[:2], full[4:])
    assert not torch.equal(window_noise(0, 2, w, 2, (16, 2)), full)  # each round: fresh noise
    assert not torch.equal(window_noise(1, 1, w, 2, (16, 2)), full)


def test_shard_is_round_robin_and_covers_everything_once():
    parts = [DistContext(rank=r, world=3).shard(list(range(10))) for r in range(3)]
    assert parts == [[0, 3, 6, 9], [1, 4, 7], [2, 5, 8]]


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the refusal on a machine without CUDA")
def test_every_stage_takes_device_and_refuses_a_missing_gpu(ddp_workspace):
    """`--device` reaches each stage: asked for CUDA on a CPU machine, every command stops
    with one line naming the device, before doing any work."""
    ws = ddp_workspace
    ckpt = ws / "train"
    for args in (["train", *TINY], ["reflow"], ["align"], ["distill"], ["run"],
                 ["eval", ckpt, "--offline"], ["eval", ckpt, "--env", "pusht", "--n-test", "1"],
                 ["bench", "latency", ckpt]):
        r = sefa(ws, *args, "--device", "cuda", check=False)
        assert r.returncode == 1, (args, r.stderr[-2000:])
        assert "device 'cuda' asked for, but CUDA is not available" in r.stderr, args
        assert "Traceback" not in r.stderr
    r = sefa(ws, "reflow", "--device", "gpu0", check=False)
    assert r.returncode == 1 and "unknown device 'gpu0'" in r.stderr


def test_device_is_recorded_and_not_part_of_the_cache_key(ddp_workspace):
    ws = ddp_workspace
    m = manifest(ws, "train")
    assert m["summary"]["device"] == "cpu" and m["processes"] == 2
    assert "device" not in m["config"]["train"]["training"]
    # the same stage asked for on another device name is still cached (auto is the CPU here)
    r = sefa(ws, "train", *TINY, "--device", "auto")
    assert ran(r) == [] and "train: cached" in r.stderr


# ---------------------------------------------------------------------------- torchrun


def test_torchrun_training_is_reused_by_status_and_a_single_process_reflow(ddp_workspace, tmp_path):
    ws = ddp_workspace
    states = {row["stage"]: row["state"]
              for row in json.loads(sefa(ws, "status", "--json").stdout)["rows"]}
    assert states["train"] == "cached"
    r = sefa(ws, "reflow", "--max-windows", "40", "--samples", "3", "--device", "cpu")
    assert ran(r) == ["reflow iter 1"] and "train: cached" in r.stderr


def test_torchrun_reflow_gives_exactly_the_single_process_couplings(ddp_workspace, tmp_path):
    """Blocks of 8 windows; with 2 ranks each rank solves every other block, rank 0 gathers
    them: the couplings are bit-identical to one process's."""
    import zarr

    ws = ddp_workspace
    # the train settings came from the command line (kept in .sefa/flags.yaml); this one is
    # the workspace's own
    (ws / "sefa.yaml").write_text("reflow:\n  batch_windows: 8\n")

    def couplings() -> dict[str, np.ndarray]:
        g = zarr.open_group(str(ws / "reflow/iter_1/couplings.zarr"), mode="r")
        return {k: g[k][:] for k in ("noise", "action", "window")}

    sefa(ws, "reflow", "--max-windows", "40", "--samples", "3", "--force")
    single = couplings()
    assert manifest(ws, "reflow/iter_1")["processes"] == 1
    r = sefa(ws, "reflow", "--max-windows", "40", "--samples", "3", "--force", nproc=2)
    assert ran(r) == ["reflow iter 1"]
    m = manifest(ws, "reflow/iter_1")
    assert m["processes"] == 2 and m["summary"]["couplings"]["solves"] == 5
    multi = couplings()
    assert multi["noise"].shape == (120, 16, 2)
    for key in single:
        np.testing.assert_array_equal(multi[key], single[key], err_msg=key)


def test_torchrun_rollouts_split_the_seeds_and_match_one_process(ddp_workspace, tmp_path):
    pytest.importorskip("gym_pusht", reason="gym-pusht (the sim extra) is not installed")
    ws = ddp_workspace
    common = ["eval", ws / "train", "--env", "pusht", "--n-test", "5", "--max-steps", "16",
              "--solver", "euler", "--steps", "2"]
    sefa(ws, *common, "--out", tmp_path / "one")
    # --force: the one-process result is cached and the cache key leaves out the world size, so
    # without it the two-process run would copy that result instead of splitting the seeds.
    r = sefa(ws, *common, "--out", tmp_path / "two", "--force", nproc=2)
    assert ": evaluated (pusht" in r.stderr, r.stderr[-2000:]
    one = json.loads((tmp_path / "one/eval_log.json").read_text())
    two = json.loads((tmp_path / "two/eval_log.json").read_text())
    assert [r["seed"] for r in two["per_seed"]] == list(range(100000, 100005))
    assert two["per_seed"] == one["per_seed"]
    assert two["test/mean_score"] == one["test/mean_score"]
