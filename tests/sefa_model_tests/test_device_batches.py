"""Training at the device's pace (sefa_model/train/device_batches.py, the lean step of the loop
and EMA), checked on the CPU: the device-resident batches are bit for bit the loader's, a run
trained on them has the loader's weights, the foreach EMA is the per-tensor one, and no step
between log steps reads a tensor back to the host.

The store is the first three real Push-T episodes (keypoints, agent state, camera images),
copied with zarr's own writer and ingested; the couplings are written by the reflow stage's
writer (sefa_model.data.couplings.write_couplings)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from sefa_data.ingest import IngestOptions, ingest
from sefa_data.store.zarr_store import EpisodeStore
from sefa_model.train import device_batches
from sefa_model.config import load_train_config
from sefa_model.data.couplings import PairSource, write_couplings
from sefa_model.train.device_batches import DeviceBatches
from sefa_model.train.ema import EMA, ema_decay
from sefa_model.data.features import window_features
from sefa_model.policy.model import FlowPolicyModel, resolve_shapes
from sefa_model.methods import Times
from sefa_model.data.windows import PolicyData
from sefa_model.train.batches import CouplingPairs, ExpertPairs, StepBatches

CPU = torch.device("cpu")
TORCH_DIR = str(Path(torch.__file__).parent)
LOWDIM = ["shape_meta.obs.keypoint.type=low_dim", "shape_meta.obs.state.dims=[0,2]",
          "policy.head=mlp", "policy.mlp_hidden_dims=[32,32]", "policy.time_embed_dim=16"]
IMAGE = ["shape_meta.obs.img.type=rgb", "shape_meta.obs.state.dims=[0,2]", "policy.head=mlp",
         "policy.crop_shape=[84,84]", "policy.mlp_hidden_dims=[32,32]", "policy.time_embed_dim=16",
         "policy.image_feature_dim=16"]
BATCH = 64
# 3 epochs' worth and more: the store's ~400 windows make 6 steps an epoch at batch 64
STEPS = [0, 1, 5, 6, 7, 12, 13]


@pytest.fixture(scope="module")
def store(shared_data, tmp_path_factory) -> Path:
    import zarr

    tmp = tmp_path_factory.mktemp("device_batches")
    src = zarr.open_group(str(shared_data / "pusht_cchi_v7_replay.zarr"), mode="r")
    ends = src["meta/episode_ends"][:3]
    small = tmp / "small.zarr"
    root = zarr.open_group(str(small), mode="w", zarr_format=2)
    for key in ("img", "keypoint", "state", "action"):
        root.create_array(f"data/{key}", data=src["data"][key][: ends[-1]])
    root.create_array("meta/episode_ends", data=ends)
    out = tmp / "store.zarr"
    ingest([small], out, IngestOptions(fps=10))
    return out


@pytest.fixture(scope="module")
def lowdim_store(store, tmp_path_factory) -> Path:
    """The same episodes without their images: the training runs' store (a run checks every
    chunk of its store first)."""
    out = tmp_path_factory.mktemp("lowdim") / "store.zarr"
    ingest([store.parent / "small.zarr"], out,
           IngestOptions(fps=10, keys=["keypoint", "state", "action"]))
    return out


def policy_data(store: Path, overrides: list[str]) -> PolicyData:
    cfg = load_train_config(None, overrides + [f"training.batch_size={BATCH}"])
    cfg = resolve_shapes(cfg, EpisodeStore.open(store))
    data = PolicyData(cfg, EpisodeStore.open(store), None)
    data.use_normalizer(data.fit_normalizer())
    return data


def couplings(data: PolicyData, path: Path, k: int = 3) -> PairSource:
    """K made-up couplings per training window, written as the reflow stage writes them."""
    n = len(data.train)
    rng = np.random.default_rng(0)
    shape = (n * k, data.cfg.policy.horizon, data.cfg.shape_meta.action.shape[-1])
    noise = rng.standard_normal(shape).astype(np.float32)
    write_couplings(path, noise, (noise * 0.5).astype(np.float32), np.repeat(np.arange(n), k),
                    data.provenance())
    return PairSource.couplings(path, "sefa_one_step")


def assert_same(a, b, where="batch"):
    """The same keys, dtypes, shapes and bits, nested dicts included."""
    if isinstance(a, dict):
        assert isinstance(b, dict) and list(a) == list(b), (where, list(a), list(b))
        for k in a:
            assert_same(a[k], b[k], f"{where}[{k}]")
        return
    if a is None or isinstance(a, Times):  # the method's training times (d: None or a tensor)
        assert type(a) is type(b), where
        if a is not None:
            assert_same({"t": a.t, "d": a.d}, {"t": b.t, "d": b.d}, where)
        return
    assert a.dtype == b.dtype and a.shape == b.shape, (where, a.dtype, b.dtype, a.shape, b.shape)
    assert torch.equal(a, b), where


def check_draws(pairs, mine: slice = slice(0, BATCH)) -> None:
    loader = StepBatches(pairs, 7, BATCH, mine)
    device = DeviceBatches(pairs, 7, BATCH, mine, CPU)
    assert device.per_epoch == len(pairs) // BATCH < max(STEPS)  # epochs are crossed
    for step in STEPS:
        a, b = loader[step], device[step]
        assert_same(a, b, f"step {step}")
        # and what the step trains on, after normalization
        for x, y in zip(pairs.to_device(a, CPU), pairs.to_device(b, CPU)):
            assert_same(x, y, f"step {step} on the device")


@pytest.mark.parametrize("mine", [slice(0, BATCH), slice(BATCH // 2, BATCH)],
                         ids=["one process", "rank 1 of 2"])
def test_base_flow_batches_on_the_device_are_the_loaders(store, mine):
    check_draws(ExpertPairs(policy_data(store, LOWDIM)), mine)


def test_image_batches_on_the_device_are_the_loaders_uint8(store):
    pairs = ExpertPairs(policy_data(store, IMAGE))
    batch = DeviceBatches(pairs, 7, BATCH, slice(0, BATCH), CPU)[0]
    assert batch["obs"]["img"].dtype == torch.uint8  # images stay uint8 where they live
    check_draws(pairs, slice(BATCH // 2, BATCH))


def test_expert_batches_with_frozen_features_on_the_device_are_the_loaders(store):
    """A student distilling the base flow on expert windows through a frozen encoder: the
    batch carries each window's features and its raw action chunk."""
    pairs = ExpertPairs(policy_data(store, LOWDIM))
    torch.manual_seed(0)
    pairs.use_features(window_features(FlowPolicyModel(pairs.data.cfg), pairs.data,
                                       pairs.windows(), CPU))
    check_draws(pairs, slice(BATCH // 2, BATCH))


@pytest.mark.parametrize("method", ["mean_flow", "shortcut"])
def test_student_batches_with_a_step_size_on_the_device_are_the_loaders(store, method):
    """Methods whose times carry a step size d besides t (sefa_model/methods)."""
    pairs = ExpertPairs(policy_data(store, LOWDIM + [f"method={method}", "flow.solver=euler",
                                                    "flow.steps=1"]))
    batch = DeviceBatches(pairs, 7, BATCH, slice(0, BATCH), CPU)[0]
    assert "d" in batch
    check_draws(pairs)


def test_ddpm_batches_on_the_device_are_the_loaders(store):
    check_draws(ExpertPairs(policy_data(store, LOWDIM + ["objective=ddpm"])))


@pytest.mark.parametrize("t_train", ["uniform", "grid", "start"])
@pytest.mark.parametrize("frozen", [False, True], ids=["observations", "frozen features"])
def test_coupling_batches_on_the_device_are_the_loaders(store, tmp_path, t_train, frozen):
    steps = 1 if t_train == "start" else 4  # what each training time samples with
    data = policy_data(store, LOWDIM + [f"flow.t_train={t_train}", "flow.solver=euler",
                                      f"flow.steps={steps}"])
    pairs = CouplingPairs(data, couplings(data, tmp_path / "couplings.zarr"))
    if frozen:
        torch.manual_seed(0)
        pairs.use_features(window_features(FlowPolicyModel(data.cfg), data, pairs.windows(), CPU))
    check_draws(pairs)
    check_draws(pairs, slice(BATCH // 2, BATCH))


def test_training_on_device_batches_gives_the_loaders_weights(lowdim_store, tmp_path, monkeypatch):
    """A whole run through train/loop.py's switch, forced on the CPU: the same weights, EMA and
    optimizer state bit for bit, and its start line says where the data lives."""
    from safetensors.torch import load_file

    from sefa_model.train.loop import Callbacks, train

    overrides = LOWDIM + ["training.max_steps=10", f"training.batch_size={BATCH}",
                          "training.val_every=10", "training.checkpoint_every=5",
                          "training.log_every=5", "training.val_batches=1",
                          "training.val_sample_windows=4", "flow.solver=euler", "flow.steps=2"]
    lines = []
    train(load_train_config(None, overrides), tmp_path / "loader", lowdim_store)
    monkeypatch.setattr(device_batches, "FORCE", True)
    train(load_train_config(None, overrides), tmp_path / "device", lowdim_store,
          callbacks=Callbacks(log=lines.append))
    assert "data on the device" in lines[0] and "0 loader workers" in lines[0]
    for name in ("model.safetensors", "ema.safetensors", "training_state/state.safetensors"):
        a = load_file(str(tmp_path / "loader/checkpoints/latest" / name))
        b = load_file(str(tmp_path / "device/checkpoints/latest" / name))
        assert a.keys() == b.keys()
        for k in a:
            assert torch.equal(a[k], b[k]), (name, k)


def test_no_step_reads_a_tensor_back_between_log_steps(lowdim_store, tmp_path, monkeypatch):
    """On a GPU every .item(), float(tensor), bool(tensor) or .tolist() in the step waits for
    the device: the loop may read tensors at log, validation and checkpoint steps only."""
    from sefa_model.train import loop as training

    state = {"in_step": False, "reads": []}

    def guard(name):
        original = getattr(torch.Tensor, name)

        def read(self, *args, **kwargs):
            caller = sys._getframe(1).f_code.co_filename
            # torch's own CPU AdamW reads its step count; the fused CUDA kernel does not
            if state["in_step"] and not caller.startswith(TORCH_DIR):
                state["reads"].append(f"{name} in {caller}:{sys._getframe(1).f_lineno}")
            return original(self, *args, **kwargs)
        monkeypatch.setattr(torch.Tensor, name, read)

    for name in ("item", "__float__", "__bool__", "__int__", "tolist", "numpy"):
        guard(name)
    step = training.optimizer_step
    batch_of = DeviceBatches.__getitem__

    def watched(f):
        def run(*args, **kwargs):
            state["in_step"] = True
            try:
                return f(*args, **kwargs)
            finally:
                state["in_step"] = False
        return run
    monkeypatch.setattr(training, "optimizer_step", watched(step))
    monkeypatch.setattr(DeviceBatches, "__getitem__", watched(batch_of))
    monkeypatch.setattr(device_batches, "FORCE", True)
    overrides = LOWDIM + ["training.max_steps=8", f"training.batch_size={BATCH}",
                          "training.val_every=8", "training.checkpoint_every=8",
                          "training.log_every=8", "training.val_batches=1",
                          "training.val_sample_windows=4", "flow.solver=euler", "flow.steps=2"]
    training.train(load_train_config(None, overrides), tmp_path / "run", lowdim_store)
    assert state["reads"] == []


def old_ema_update(ema: EMA, model: torch.nn.Module, step: int) -> None:
    """The per-tensor EMA update the foreach one replaced, as it was written."""
    decay = ema_decay(step - 1, ema.power, ema.inv_gamma, ema.max_decay)
    with torch.no_grad():
        for ema_p, p in zip(ema.model.parameters(), model.parameters()):
            if p.requires_grad:
                ema_p.mul_(decay).add_(p.detach(), alpha=1 - decay)
            else:
                ema_p.copy_(p)
        for ema_b, b in zip(ema.model.buffers(), model.buffers()):
            ema_b.copy_(b)


def test_foreach_ema_is_the_per_tensor_ema_bit_for_bit():
    torch.manual_seed(0)
    model = torch.nn.Sequential(torch.nn.Linear(7, 33), torch.nn.BatchNorm1d(33),
                                torch.nn.Linear(33, 5))
    model[0].requires_grad_(False)  # a frozen part, copied rather than averaged
    new, old = EMA(model), EMA(model)
    for step in range(1, 40):
        with torch.no_grad():
            for p in model.parameters():
                p.add_(torch.randn_like(p) * 0.1)
        model.train()(torch.randn(16, 7))  # moves BatchNorm's running statistics (buffers)
        new.update(model, step)
        old_ema_update(old, model, step)
        for a, b in zip(new.model.state_dict().values(), old.model.state_dict().values()):
            assert torch.equal(a, b), step
    assert not torch.equal(new.model[2].weight, model[2].weight)  # it does average


def test_device_path_is_off_on_the_cpu_and_the_optimizer_is_torchs_default(store):
    """The CPU keeps the loader and torch's default AdamW, so its numbers do not move."""
    from sefa_model.train.loop import adamw_kernel

    pairs = ExpertPairs(policy_data(store, LOWDIM))
    cfg = pairs.data.cfg
    assert device_batches.resident_batches(pairs, cfg, 0, slice(0, BATCH), CPU) is None
    p = torch.nn.Parameter(torch.zeros(3))
    default = torch.optim.AdamW([p]).param_groups[0]
    ours = torch.optim.AdamW([p], **adamw_kernel(CPU)).param_groups[0]
    assert ours == {**default, "params": ours["params"]}
    assert adamw_kernel(torch.device("cuda")) == {"fused": True, "foreach": None}


def test_bench_scale_puts_the_floor_beside_each_rate(lowdim_store, tmp_path):
    """benchmarks/bench_scale.py (the GPU acceptance run's rows, here on the CPU at a tiny
    budget): the loop and the bare step of the same network in one process, and one-step
    predict_action beside the bare forward."""
    from benchmark_module import load

    bench = load("bench_scale")
    tiny = LOWDIM + ["training.lr=1e-3", "training.val_batches=1", "training.val_sample_windows=4"]
    rows = bench.train_rows("MLP", lowdim_store, tmp_path / "mlp", tiny, "cpu", 10, rounds=1)
    assert [r[0] for r in rows] == ["train steps/s, MLP, batch 256",
                                    "  bare step steps/s, MLP (the floor)", "  loop / bare, MLP"]
    assert rows[0][1] > 0 and rows[1][1] > 0 and rows[2][1] == rows[0][1] / rows[1][1]
    lat = dict(bench.latency_rows(tmp_path / "mlp" / "round0", lowdim_store, "cpu", 5))
    # the rows and their ratio; which is faster is the benchmark's finding, not asserted here (a
    # 5-call timing flips on a loaded machine)
    call, floor = lat["predict_action p50 ms, one-step (Euler-1)"], lat["  bare forward p50 ms (the floor)"]
    assert call > 0 and floor > 0 and lat["  predict_action / bare forward"] == call / floor
