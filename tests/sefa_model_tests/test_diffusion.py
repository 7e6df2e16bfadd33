"""The diffusion baseline (issue 6): Diffusion Policy's schedule and samplers on our network,
`sefa train --objective ddpm`, and sampling it through the same Policy as the flows."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from cli_inprocess import run_cli
from sefa_data.errors import SefaInputError
from sefa_data.ingest import IngestOptions, ingest
from sefa_model.config import DiffusionConfig, load_train_config
from sefa_model.methods.diffusion import ddpm_loss, ddpm_step, denoise, make_scheduler
from sefa_model.policy.artifact import Policy
from sefa_model.train.loop import train

REPO = Path(__file__).resolve().parents[2]

TINY = ["shape_meta.obs.keypoint.type=low_dim", "shape_meta.obs.state.dims=[0,2]",
        "policy.head=mlp", "policy.mlp_hidden_dims=[128,128]", "policy.time_embed_dim=32",
        "training.batch_size=128", "training.lr=1e-3", "training.lr_warmup_steps=20",
        "training.val_batches=1", "training.val_sample_windows=64", "training.log_every=50"]


def squared_cosine_alphas_cumprod(n: int) -> np.ndarray:
    """Nichol & Dhariwal's schedule as Diffusion Policy configures it (squaredcos_cap_v2),
    written out independently of diffusers: beta_i = min(1 - abar((i+1)/n) / abar(i/n), 0.999)."""
    def abar(t):
        return math.cos((t + 0.008) / 1.008 * math.pi / 2) ** 2
    betas = np.array([min(1 - abar((i + 1) / n) / abar(i / n), 0.999) for i in range(n)])
    return np.cumprod(1 - betas)


def point_mass_eps(c: torch.Tensor, scheduler):
    """The exact noise predictor when every chunk equals c: eps = (x_k - sqrt(abar_k) c) / sqrt(1 - abar_k)."""
    abar = scheduler.alphas_cumprod.double()

    def eps(x, k):
        a = abar[k].view(-1, 1, 1)
        return ((x.double() - a.sqrt() * c) / (1 - a).sqrt()).to(x.dtype)
    return eps


def test_schedule_is_diffusion_policys_squared_cosine():
    cfg = DiffusionConfig()
    assert (cfg.num_train_timesteps, cfg.beta_schedule, cfg.clip_sample, cfg.inference_steps) == \
        (100, "squaredcos_cap_v2", True, 100)
    s = make_scheduler(cfg)
    np.testing.assert_allclose(s.alphas_cumprod.numpy(), squared_cosine_alphas_cumprod(100), rtol=1e-4, atol=1e-9)
    x1, noise, k = torch.randn(4, 16, 2), torch.randn(4, 16, 2), torch.tensor([0, 10, 50, 99])
    a = torch.as_tensor(squared_cosine_alphas_cumprod(100), dtype=torch.float32)[k].view(-1, 1, 1)
    torch.testing.assert_close(s.add_noise(x1, noise, k), a.sqrt() * x1 + (1 - a).sqrt() * noise)


@pytest.mark.parametrize("sampler,steps", [("ddpm", 100), ("ddim", 10), ("ddim", 1)])
def test_samplers_recover_a_point_mass_with_the_exact_noise_predictor(sampler, steps):
    cfg = DiffusionConfig()
    c = torch.linspace(-0.9, 0.9, 32).view(1, 16, 2).double()
    sched = make_scheduler(cfg, sampler)
    noise = torch.randn(8, 16, 2, generator=torch.Generator().manual_seed(0))
    out = denoise(point_mass_eps(c, sched), noise, cfg, sampler=sampler, steps=steps,
                  generator=torch.Generator().manual_seed(1), scheduler=sched)
    assert out.nfe == steps
    torch.testing.assert_close(out.x.double(), c.expand(8, -1, -1), atol=1e-4, rtol=0)
    # and the loss of that predictor is zero at any timestep
    k = torch.arange(0, 100, 13)
    x1 = c.float().expand(len(k), -1, -1)
    loss = ddpm_loss(point_mass_eps(c, sched), torch.randn(len(k), 16, 2), x1, k, sched)
    assert float(loss) < 1e-10


@pytest.mark.parametrize("k", [99, 60, 1, 0])
def test_ddpm_step_with_given_noise_is_diffusers_step(k):
    """Sampling draws a trajectory's noise in one call and feeds it to our DDPM step; that step
    must be diffusers' DDPMScheduler.step (DP's settings) bit for bit, given the same noise."""
    scheduler = make_scheduler(DiffusionConfig())
    scheduler.set_timesteps(100)
    x, eps = torch.randn(4, 16, 2) * 2, torch.randn(4, 16, 2)
    theirs = scheduler.step(eps, k, x, generator=torch.Generator().manual_seed(3)).prev_sample
    noise = torch.randn(x.shape, generator=torch.Generator().manual_seed(3))
    assert torch.equal(ddpm_step(scheduler, eps, k, x, noise), theirs)
    assert k == 0 or not torch.equal(ddpm_step(scheduler, eps, k, x, -noise), theirs)


def test_ddpm_steps_use_fresh_noise_and_the_generator_makes_them_repeatable():
    cfg = DiffusionConfig()
    zero = lambda x, k: torch.zeros_like(x)  # noqa: E731
    noise = torch.zeros(2, 16, 2)
    a = denoise(zero, noise, cfg, generator=torch.Generator().manual_seed(3)).x
    b = denoise(zero, noise, cfg, generator=torch.Generator().manual_seed(3)).x
    c = denoise(zero, noise, cfg, generator=torch.Generator().manual_seed(4)).x
    assert torch.equal(a, b) and not torch.equal(a, c)
    ddim = denoise(zero, noise, cfg, sampler="ddim", steps=10).x
    assert torch.equal(ddim, torch.zeros_like(ddim))  # deterministic: no noise is added
    with pytest.raises(ValueError, match="steps must be in"):
        denoise(zero, noise, cfg, sampler="ddim", steps=101)


@pytest.fixture(scope="module")
def ddpm_run(shared_data, tmp_path_factory) -> tuple[Path, Path]:
    store = tmp_path_factory.mktemp("pusht") / "dataset.zarr"
    ingest([shared_data / "pusht_cchi_v7_replay.zarr"], store,
           IngestOptions(fps=10, keys=["keypoint", "state", "action"]))
    run = store.parent / "ddpm"
    cfg = load_train_config(None, TINY + ["objective=ddpm", "training.max_steps=300",
                                          "training.val_every=150", "training.checkpoint_every=150"])
    train(cfg, run, store)
    return run, store


def test_ddpm_training_on_pusht_learns_and_records_its_convention(ddpm_run):
    run, _ = ddpm_run
    logs = [json.loads(line) for line in (run / "logs.jsonl").read_text().splitlines()]
    losses = [r["train_loss"] for r in logs if "train_loss" in r]
    assert losses[-1] < 0.5 * losses[0], losses
    final = logs[-1]
    assert final["val_nfe"] == 100  # validated with its own sampler, DDPM-100
    assert final["val_action_mse"] < 0.6 * final["val_mean_action_mse"], final
    meta = json.loads((run / "checkpoints" / "latest" / "config.json").read_text())
    assert meta["kind"] == "ddpm" and meta["train_config"]["objective"] == "ddpm"
    assert meta["diffusion_convention"]["prediction"] == "epsilon"


def test_ddpm_policy_samples_with_ddpm_and_ddim_and_refuses_ode_solvers(ddpm_run):
    run, _ = ddpm_run
    policy = Policy.load(run)
    obs = {"keypoint": np.full((2, 9, 2), 250, np.float32), "state": np.full((2, 5), 250, np.float32)}
    own = policy.predict_action(obs, generator=torch.Generator().manual_seed(0))
    again = policy.predict_action(obs, generator=torch.Generator().manual_seed(0))
    assert own.nfe == 100 and torch.equal(own.action, again.action)
    assert own.action.shape == (1, 8, 2) and torch.isfinite(own.action).all()
    assert policy.predict_action(obs, solver="ddim", steps=10).nfe == 10
    with pytest.raises(SefaInputError, match="solver 'euler' does not apply to a ddpm policy"):
        policy.predict_action(obs, solver="euler", steps=1)


def test_reflow_refuses_a_diffusion_checkpoint(ddpm_run, tmp_path):
    from sefa_model.sefa.reflow import CouplingConfig, generate_couplings

    run, store = ddpm_run
    with pytest.raises(SefaInputError, match="reflow needs a rectified-flow policy"):
        generate_couplings(Policy.load(run), store, tmp_path / "c.zarr", CouplingConfig(max_windows=4))
    assert not (tmp_path / "c.zarr").exists()


def test_cli_trains_the_baseline_with_objective_flag_and_evaluates_ddim(ddpm_run, tmp_path):
    _, store = ddpm_run
    ws = store.parent
    out = tmp_path / "ddpm_cli"

    def sefa(*args):  # in-process through sefa_cli.main.main (tests/cli_inprocess.py)
        return run_cli(*args, "-w", ws, cwd=REPO)
    r = sefa("train", *TINY, "training.max_steps=20", "training.val_every=20", "--objective", "ddpm",
             "--out", out, "--json")
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["steps"] == 20
    r = sefa("eval", out, "--offline", "--solver", "ddim", "--steps", "5", "--windows", "16",
             "--samples", "2", "--json")
    assert r.returncode == 0, r.stderr
    row = json.loads(r.stdout)[0]
    assert (row["kind"], row["solver"], row["steps"], row["nfe"]) == ("ddpm", "ddim", 5, 5)
    r = sefa("train", "--objective", "score", "--out", tmp_path / "x")
    assert r.returncode == 1 and r.stderr.count("\n") == 1 and "objective" in r.stderr
