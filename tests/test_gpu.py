"""The GPU check (`make gpu-check`): every test here needs CUDA and is skipped without it, so it
never fails on a CPU machine. It covers device placement of every stage, bf16 training, NCCL
with the GPUs present, reflow on the GPU against the CPU, and CUDA-synchronised latency."""

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

pytestmark = [pytest.mark.gpu,
              pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")]

REPO = Path(__file__).resolve().parents[1]
TINY = ["shape_meta.obs.keypoint.type=low_dim", "shape_meta.obs.state.dims=[0,2]",
        "policy.head=mlp", "policy.mlp_hidden_dims=[256,256]", "training.max_steps=60",
        "training.batch_size=256", "training.lr=1e-3", "training.lr_warmup_steps=5",
        "training.val_every=60", "training.checkpoint_every=60", "training.log_every=20",
        "training.val_batches=1", "training.val_sample_windows=16"]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def sefa(ws: Path, *args, nproc: int = 0) -> subprocess.CompletedProcess:
    launcher = ([] if not nproc else ["-m", "torch.distributed.run", "--nproc_per_node", str(nproc),
                                       "--master_addr", "127.0.0.1", "--master_port", str(free_port())])
    r = subprocess.run([sys.executable, *launcher, "-m", "sefa_cli.main", *map(str, args), "-w", str(ws)],
                       capture_output=True, text=True, cwd=REPO, timeout=900)
    assert r.returncode == 0, r.stderr[-3000:]
    return r


@pytest.fixture(scope="module")
def ws(shared_data, tmp_path_factory) -> Path:
    ws = tmp_path_factory.mktemp("gpu")
    sefa(ws, "ingest", shared_data / "pusht_cchi_v7_replay.zarr", "--fps", "10",
         "--key", "keypoint", "--key", "state", "--key", "action")
    n = torch.cuda.device_count()
    r = sefa(ws, "train", *TINY, "--device", "cuda", nproc=n)  # NCCL with every GPU present
    assert "bf16 autocast" in r.stderr and "cuda:0" in r.stderr, r.stderr
    sefa(ws, "reflow", "--max-windows", "64", "--samples", "4", "--device", "cuda", nproc=n)
    sefa(ws, "align", "--eps", "0.2", "--device", "cuda")
    sefa(ws, "distill", "--device", "cuda", nproc=n)
    return ws


def test_every_stage_ran_on_the_gpu(ws):
    for artifact in ("train", "distill"):
        m = json.loads((ws / artifact / "manifest.json").read_text())
        assert m["summary"]["device"] == "cuda" and m["processes"] == torch.cuda.device_count()
    m = json.loads((ws / "reflow/iter_1/manifest.json").read_text())
    assert m["summary"]["couplings"]["device"].startswith("cuda")
    r = sefa(ws, "eval", ws / "distill", "--offline", "--device", "cuda", "--json")
    assert json.loads(r.stdout)[0]["device"].startswith("cuda")


def test_reflow_on_the_gpu_matches_the_cpu(ws, tmp_path):
    from sefa_model.policy.artifact import Policy
    from sefa_model.sefa.reflow import CouplingConfig, generate_couplings
    import zarr

    cfg = CouplingConfig(samples_per_window=4, max_windows=32)
    out = {}
    for dev in ("cpu", "cuda"):
        generate_couplings(Policy.load(ws / "train", device=dev), ws / "dataset.zarr",
                           tmp_path / dev, cfg)
        out[dev] = zarr.open_group(str(tmp_path / dev), mode="r")
    np.testing.assert_array_equal(out["cpu"]["noise"][:], out["cuda"]["noise"][:])  # CPU-drawn
    # TF32 matmuls and a different summation order: agreement within the solver's tolerance
    np.testing.assert_allclose(out["cuda"]["action"][:], out["cpu"]["action"][:], atol=2e-2)


def test_reflow_with_the_field_captured_gives_the_eager_couplings(ws, tmp_path):
    """The default on CUDA: reflow's RK45 replays the velocity field as a CUDA graph (one per
    block size: 3 blocks of 16 windows and one of 8 here); the couplings and the NFE are the
    eager ones."""
    from sefa_model.data.couplings import read_couplings
    from sefa_model.policy.artifact import Policy
    from sefa_model.sefa.reflow import CouplingConfig, generate_couplings

    policy = Policy.load(ws / "train", device="cuda")
    cfg = CouplingConfig(samples_per_window=4, max_windows=56, batch_windows=16)
    got = {}
    for capture in (True, False):
        summary = generate_couplings(policy, ws / "dataset.zarr", tmp_path / str(capture), cfg,
                                     capture=capture)
        assert summary["cuda_graphs"] is capture
        got[capture] = (read_couplings(tmp_path / str(capture)).action, summary["nfe"])
    # a replay runs the recorded kernels, normally the eager bits; should cuBLAS pick another
    # kernel under capture, RK45's shared step may round otherwise: within its tolerance
    assert abs(got[True][1] - got[False][1]) <= 0.05 * got[False][1]
    np.testing.assert_allclose(got[True][0], got[False][0], atol=1e-3, rtol=0)


def test_predict_action_on_the_gpu_same_noise_as_cpu_and_compiled_equals_eager(ws):
    from sefa_model.policy.artifact import Policy

    obs = {"keypoint": np.zeros((2, 9, 2), np.float32) + 200, "state": np.zeros((2, 5), np.float32) + 250}
    cpu = Policy.load(ws / "distill", device="cpu")
    gpu = Policy.load(ws / "distill", device="cuda")
    a = cpu.predict_action(obs, generator=torch.Generator().manual_seed(0)).action_pred
    b = gpu.predict_action(obs, generator=torch.Generator().manual_seed(0)).action_pred
    assert b.device.type == "cuda"
    torch.testing.assert_close(b.cpu(), a, atol=5e-2, rtol=0)
    gpu.predict_action(obs, generator=torch.Generator(device="cuda").manual_seed(0))  # a CUDA generator works
    compiled = Policy.load(ws / "distill", device="cuda").compile()
    for _ in range(3):  # compile, record the CUDA graph, replay
        c = compiled.predict_action(obs, generator=torch.Generator().manual_seed(0)).action_pred
    torch.testing.assert_close(c, b, atol=1e-3, rtol=0)


def test_cuda_synchronised_latency(ws):
    from sefa_model.eval.latency import bench_latency

    out = bench_latency([f"{ws}/train@euler-1", f"{ws}/distill"], store=ws / "dataset.zarr",
                        device="cuda", calls=50, warmup=10, max_seconds=10)
    assert out["device"].startswith("cuda") and out["machine"]["gpu"]
    for row in out["rows"]:
        assert 0 < row["forward_ms"] <= row["p50_ms"] * 1.5


def test_image_pipeline_on_the_gpu(shared_data, tmp_path):
    """Issue 14 on a GPU: a ResNet-18 image policy (DP's encoder) trains under bf16, its frozen
    features are cached once on the GPU and agree with the CPU's, and it runs in closed loop."""
    pytest.importorskip("gym_pusht", reason="gym-pusht (the sim extra) is not installed")
    ws = tmp_path / "img"
    sefa(ws, "ingest", shared_data / "pusht_cchi_v7_replay.zarr", "--fps", "10",
         "--key", "img", "--key", "state", "--key", "action")
    tiny_image = ["shape_meta.obs.img.type=rgb", "shape_meta.obs.state.dims=[0,2]",
                  "policy.image_encoder=resnet18", "policy.crop_shape=[84,84]", "policy.head=mlp",
                  "policy.mlp_hidden_dims=[256,256]", "training.max_steps=20", "training.batch_size=64",
                  "training.val_every=20", "training.checkpoint_every=20", "training.val_batches=1",
                  "training.val_sample_windows=16"]
    r = sefa(ws, "train", *tiny_image, "--device", "cuda")
    assert "bf16 autocast" in r.stderr
    sefa(ws, "reflow", "--max-windows", "64", "--samples", "2", "--device", "cuda")
    sefa(ws, "distill", "--device", "cuda")
    (entry,) = (ws / "features").iterdir()  # one encoding, shared by reflow and distill

    from safetensors.torch import load_file

    from sefa_data.store.zarr_store import EpisodeStore
    from sefa_model.data.features import window_features
    from sefa_model.policy.artifact import Policy
    from sefa_model.data.windows import PolicyData

    stored = load_file(str(entry / "features.safetensors"))
    cpu = Policy.load(ws / "train", device="cpu")
    data = PolicyData(cpu.cfg, EpisodeStore.open(ws / "dataset.zarr"), cpu.normalizer)
    again = window_features(cpu.model, data, stored["windows"].numpy(), torch.device("cpu"))
    torch.testing.assert_close(stored["features"], again, rtol=1e-3, atol=1e-3)
    out = json.loads(sefa(ws, "eval", ws / "distill", "--env", "pusht", "--n-test", "2",
                          "--max-steps", "32", "--device", "cuda", "--json").stdout)
    assert out[0]["n_test"] == 2


def test_captured_one_step_policy_equals_eager_and_other_batches_stay_eager(ws):
    """The default on CUDA: a batch-1 call of a fixed-step sampler replays a CUDA graph of the
    encoder and the sampler; its actions are the eager ones, and other batches run eager."""
    from sefa_model.policy.artifact import Policy

    obs = {"keypoint": np.zeros((9, 2), np.float32) + 200, "state": np.zeros((2,), np.float32) + 250}
    graphed = Policy.load(ws / "distill", device="cuda")
    eager = Policy.load(ws / "distill", device="cuda")
    eager.capture = False
    assert graphed.capture
    for seed in range(3):  # record, then replay with new inputs
        noise = torch.randn(1, graphed.cfg.policy.horizon, 2, generator=torch.Generator().manual_seed(seed))
        a = graphed.predict_action(obs, noise=noise).action_pred
        b = eager.predict_action(obs, noise=noise).action_pred
        torch.testing.assert_close(a, b, atol=1e-5, rtol=0)
    assert len(graphed._graphs) == 1 and None not in graphed._graphs.values()
    two = {k: np.stack([v, v]) for k, v in obs.items()}
    graphed.predict_action(two)
    assert len(graphed._graphs) == 1  # batch 2: eager


def test_device_batches_on_the_gpu_are_the_loaders_copied(ws):
    """The data-on-the-device path on CUDA draws the loader's batches (the same windows, noise
    and t; the values compared on the host)."""
    from sefa_data.store.zarr_store import EpisodeStore
    from sefa_model.config import load_train_config
    from sefa_model.train.device_batches import DeviceBatches, resident_batches
    from sefa_model.policy.model import resolve_shapes
    from sefa_model.data.windows import PolicyData
    from sefa_model.train.batches import ExpertPairs, StepBatches

    store = EpisodeStore.open(ws / "dataset.zarr")
    cfg = resolve_shapes(load_train_config(None, TINY), store)
    data = PolicyData(cfg, store, None)
    data.use_normalizer(data.fit_normalizer())
    pairs = ExpertPairs(data)
    cuda = torch.device("cuda")
    assert resident_batches(pairs, cfg, 0, slice(0, 256), cuda) is not None
    device = DeviceBatches(pairs, 3, 256, slice(128, 256), cuda)
    loader = StepBatches(pairs, 3, 256, slice(128, 256))
    for step in (0, 1, device.per_epoch, device.per_epoch + 1):
        a, b = loader[step], device[step]
        for k in ("x0", "t"):
            assert b[k].device.type == "cuda" and torch.equal(a[k], b[k].cpu())
        for k in a["obs"]:
            assert torch.equal(a["obs"][k], b["obs"][k].cpu())
