"""Students as methods (sefa_model/methods): each built-in student trains from a tiny base,
samples at its NFE, exports and serves; the registry refuses unknown names in one line; a
method added in one file, exactly as docs/extending.md shows it, trains through `sefa distill`;
the math of the new students on cases with a known answer."""

from __future__ import annotations

import re
import types
from pathlib import Path

import numpy as np
import pytest
import torch

from cli_inprocess import run_cli
from deploy_helpers import TINY, student_workspace

REPO = Path(__file__).resolve().parents[2]
STUDENTS = ("rfpp", "mean_flow", "shortcut")
# each student's export format: ONNX (seconds per export) for one with a step input, TorchScript
# for the others; every format runs the same traced sampler
FORMATS = {"rfpp": "torchscript", "mean_flow": "onnx", "shortcut": "torchscript"}
OBS = {"keypoint": np.full((1, 2, 9, 2), 200.0, np.float32), "state": np.full((1, 2, 5), 200.0, np.float32)}


def train_student(ws: Path, method: str, out: Path) -> Path:
    from sefa_pipelines.stages import student_config
    from sefa_model.config import load_train_config
    from sefa_model.data.couplings import PairSource
    from sefa_model.methods import get
    from sefa_model.train.loop import train

    cfg = student_config(load_train_config(None, TINY), [], method=method)
    pairs = PairSource.couplings(ws / "couplings.zarr", "reflow_one_step")
    train(cfg, out, ws / "dataset.zarr", init_from=ws / "flow" / "checkpoints" / "latest",
          couplings=pairs if get(method).pairs == "couplings" else None,
          features_cache=ws / "features")
    return out / "checkpoints" / "latest"


@pytest.fixture(scope="module")
def students(deploy_workspace, tmp_path_factory):
    root = tmp_path_factory.mktemp("students")
    return {m: train_student(deploy_workspace, m, root / m) for m in STUDENTS}


@pytest.mark.parametrize("method", STUDENTS)
def test_each_student_trains_samples_at_one_evaluation_exports_and_serves(students, method, tmp_path):
    from sefa_deploy.export import export_policy
    from sefa_model.policy.artifact import Policy

    ckpt = students[method]
    policy = Policy.load(ckpt, device="cpu")
    config = __import__("json").loads((ckpt / "config.json").read_text())
    assert config["train_config"]["method"] == method
    pred = policy.predict_action(OBS)
    assert pred.nfe == 1 and torch.isfinite(pred.action).all()
    # the export's own parity check (against this checkpoint) must pass, and it runs one step
    if FORMATS[method] == "onnx":
        pytest.importorskip("onnxruntime", reason="the deploy extra is not installed")
    out = tmp_path / "export"
    export_policy(ckpt, out, fmt=FORMATS[method])
    from sefa_deploy.backends import load_backend

    # what the server runs per request: the export's backend on one observation and noise
    backend = load_backend(out, device="cpu")
    noise = np.random.default_rng(0).standard_normal((1, 16, 2)).astype(np.float32)
    action, chunk = backend({k: v for k, v in OBS.items()}, noise)
    want = policy.predict_action(OBS, noise=torch.from_numpy(noise))
    np.testing.assert_allclose(chunk, want.action_pred.numpy(), rtol=1e-4, atol=1e-3)


def test_a_student_with_a_step_input_starts_as_the_base_flow_at_every_step_size(deploy_workspace):
    """The step embedding is zero at initialisation: before training, the student's velocity
    is the base flow's, whatever step size it is given (a fine-tune starts from the teacher)."""
    from sefa_pipelines.stages import student_config
    from sefa_model.policy.checkpoint import load_weights, open_policy
    from sefa_model.config import saved_train_config
    from sefa_model.policy.model import FlowPolicyModel, resolve_shapes
    from sefa_data.store.zarr_store import EpisodeStore

    path, meta, weights = open_policy(deploy_workspace / "flow" / "checkpoints" / "latest")
    store = EpisodeStore.open(deploy_workspace / "dataset.zarr")
    base_cfg = resolve_shapes(saved_train_config(meta["train_config"], "base"), store)
    base = FlowPolicyModel(base_cfg)
    load_weights(base, weights)
    student = FlowPolicyModel(resolve_shapes(student_config(base_cfg, [], method="mean_flow"), store))
    load_weights(student, weights, new_ok=("head.step_encoder.",))
    gen = torch.Generator().manual_seed(0)
    x, cond = torch.randn(4, 16, 2, generator=gen), torch.randn(4, base.obs_encoder.out_dim, generator=gen)
    t = torch.rand(4, generator=gen)
    for d in (None, 0.25, 1.0):
        torch.testing.assert_close(student.velocity(x, t, cond, d), base.velocity(x, t, cond), rtol=0, atol=0)


def test_mean_flow_target_is_the_average_velocity_of_a_known_flow():
    """On the field v(z, t) = -z (solution z_s = z_t e^-(s-t)), the exact average velocity over
    [t, t + d] is z (e^-d - 1) / d. With u equal to it, the MeanFlow target v + d du/dt (the
    derivative along (v, 1, -1)) must return u itself: a fixed point, so zero loss."""
    from sefa_model.methods import StepCalls, Times
    from sefa_model.methods.mean_flow import METHOD

    def u(z, t, d):
        d = d.view(-1, 1, 1)
        return z * torch.where(d > 0, torch.expm1(-d) / d.clamp_min(1e-12), -torch.ones_like(d))

    x0 = torch.randn(64, 4, 2, dtype=torch.float64)
    x1 = torch.randn(64, 4, 2, dtype=torch.float64)
    gen = torch.Generator().manual_seed(1)
    times = METHOD.draw(None, 64, gen)
    times = Times(times.t.double(), times.d.double())
    calls = StepCalls(f=u, target=u, teacher=lambda z, t, d=None: -z)
    assert float(METHOD.loss(None, calls, x0, x1, times)) < 1e-18
    # and a wrong u (the instantaneous velocity everywhere) is not a fixed point
    wrong = lambda z, t, d: -z  # noqa: E731
    assert float(METHOD.loss(None, StepCalls(wrong, wrong, lambda z, t, d=None: -z), x0, x1, times)) > 1e-3


def test_shortcut_targets_are_two_half_steps_of_the_model_itself():
    """The self-consistency target of a step 2d is the mean of two steps of d taken with the
    model's own predictions; with a model that is exact for v(z, t) = 1 (any step: 1), the
    loss is zero, and with one that is not, it is not."""
    from sefa_model.methods import StepCalls
    from sefa_model.methods.shortcut import METHOD

    gen = torch.Generator().manual_seed(2)
    times = METHOD.draw(None, 256, gen)
    assert (times.d > 0).any() and (times.d == 0).any() and float((times.t + times.d).max()) <= 1
    one = lambda z, t, d=None: torch.ones_like(z)  # noqa: E731
    calls = StepCalls(one, one, one, rows=lambda mask: StepCalls(one, one, one))
    x = torch.randn(256, 4, 2)
    assert float(METHOD.loss(None, calls, x, x, times)) == 0.0
    drifting = lambda z, t, d=None: torch.ones_like(z) * (1 + (0 if d is None else d.view(-1, 1, 1)))  # noqa: E731
    calls = StepCalls(drifting, drifting, one, rows=lambda mask: StepCalls(drifting, drifting, one))
    assert float(METHOD.loss(None, calls, x, x, times)) > 0


def test_u_shaped_times_follow_their_density():
    from sefa_model.methods.rfpp import u_shaped_t

    t = u_shaped_t(200_000, 4.0, torch.Generator().manual_seed(0))
    hist, _ = np.histogram(t.numpy(), bins=10, range=(0, 1))
    edges = np.linspace(0, 1, 11)
    cdf = (np.sinh(4 * (edges - 0.5)) + np.sinh(2)) / (2 * np.sinh(2))
    np.testing.assert_allclose(hist / len(t), np.diff(cdf), atol=0.003)


def test_an_unknown_method_is_one_line_listing_the_valid_names_nearest_first(tmp_path):
    r = run_cli("distill", "--method", "mean_flw", "-w", tmp_path, cwd=REPO)
    assert r.returncode != 0
    lines = [line for line in r.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    # named as typed (not a .sefa/flags.yaml that does not exist), students only
    assert lines[0].startswith("error: --method: unknown method 'mean_flw' (students, nearest "
                               "first: mean_flow, "), lines[0]
    assert "flow," not in lines[0].replace("mean_flow,", "") and "ddpm" not in lines[0]


def test_the_extending_guide_example_is_a_method_in_one_file(deploy_workspace, tmp_path):
    """docs/extending.md's example, taken from the page itself, registered as that page says,
    then trained through `sefa distill --method l1_student` in a workspace and sampled at one
    network evaluation."""
    from sefa_model import methods
    from sefa_model.policy.artifact import Policy

    page = (REPO / "docs" / "extending.md").read_text()
    code = [b for b in re.findall(r"```python\n(.*?)```", page, re.S) if "METHOD = " in b][0]
    module = types.ModuleType("l1_student")
    exec(compile(code, "docs/extending.md", "exec"), module.__dict__)
    methods.register(module.METHOD)
    try:
        ws = student_workspace(deploy_workspace, tmp_path / "ws", "l1_student")
        r = run_cli("distill", "--yes", "-w", ws, cwd=REPO)
        assert r.returncode == 0, r.stderr[-2000:]
        policy = Policy.load(ws / "distill" / "checkpoints" / "latest", device="cpu")
        assert policy.predict_action(OBS).nfe == 1
    finally:
        methods._REGISTRY.pop("l1_student", None)


def test_a_frozen_encoder_student_on_fresh_noise_draws_the_base_flows_batches(deploy_workspace):
    """A student that distils the base flow on fresh noise (its encoder frozen: each window's
    condition instead of its observation) draws, for a step, the same windows, noise and
    expert chunks as the base flow's own loader; only the times are its method's."""
    from sefa_pipelines.stages import student_config
    from sefa_data.store.zarr_store import EpisodeStore
    from sefa_model.config import load_train_config
    from sefa_model.policy.model import resolve_shapes
    from sefa_model.data.windows import PolicyData
    from sefa_data.normalizer import Normalizer
    from sefa_model.train.batches import ExpertPairs, batch_indices, step_generator

    store = EpisodeStore.open(deploy_workspace / "dataset.zarr")
    norm = Normalizer.load(deploy_workspace / "flow" / "checkpoints" / "latest")
    base_cfg = resolve_shapes(load_train_config(None, TINY), store)
    student_cfg = resolve_shapes(student_config(load_train_config(None, TINY), [], method="shortcut"), store)
    base = ExpertPairs(PolicyData(base_cfg, store, norm))
    student = ExpertPairs(PolicyData(student_cfg, store, norm))
    features = torch.randn(len(student), 7)
    student.use_features(features)
    for step in (0, 5):
        idx = batch_indices(0, step, len(base), 64)
        b = base.to_device(base.fetch(idx, step_generator(0, step), slice(8, 40)), torch.device("cpu"))
        s = student.to_device(student.fetch(idx, step_generator(0, step), slice(8, 40)), torch.device("cpu"))
        torch.testing.assert_close(s[1], b[1], rtol=0, atol=0)  # the noise
        torch.testing.assert_close(s[2], b[2], rtol=0, atol=0)  # the expert chunks
        torch.testing.assert_close(s[0], features[idx[8:40]], rtol=0, atol=0)  # each window's condition
        assert s[3].d is not None and b[3].d is None
