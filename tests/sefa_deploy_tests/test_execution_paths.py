"""Every execution mode on a tiny one-step checkpoint through `sefa eval --env pusht` and through
the server's `step` path, with the same seed: the same actions, step by step (the executor is
one owner, so a policy scores in simulation what it does when served). Push-T's episode runs
in process both ways; the server path is `PolicyService.handle` with a connection's session
(what `sefa serve` does minus the socket; tests/sefa_deploy_tests/test_serve.py drives a real
server)."""

from __future__ import annotations

import asyncio
import json

import numpy as np
import pytest

pytest.importorskip("pymunk", reason="the sim extra is not installed")

from sefa_model.policy.execution import ExecutionSettings as E  # noqa: E402
from sefa_sim.pusht import PushTEnv as REAL_ENV  # noqa: E402

SEED, STEPS = 100_000, 24
# `sefa eval`'s options, and the same as the server's settings (None: the default)
MODES = {
    "receding-8": ([], None),
    "receding-1": (["--execution", "receding", "--replan-every", "1"], E("receding", 1)),
    "ensemble-1": (["--execution", "ensemble"], E("ensemble")),
    "coherent-2x4": (["--execution", "coherent", "--replan-every", "2", "--samples", "4"],
                     E("coherent", 2, 4)),
    "bid-1x6": (["--execution", "bid", "--samples", "6", "--weak", "flow@euler-1"],
                E("bid", samples=6, weak="flow@euler-1")),
}


class RecordingEnv:
    """Push-T, recording every action it is given."""

    def __init__(self):
        self.env, self.actions = REAL_ENV(), []

    def __getattr__(self, name):
        return getattr(self.env, name)

    def step(self, action):
        self.actions.append(np.asarray(action, np.float64).copy())
        return self.env.step(action)


def served_actions(ws, settings) -> tuple[list[np.ndarray], float]:
    """One Push-T episode through the server's step path: (its actions, best coverage)."""
    from sefa_deploy.backends import load_backend
    from sefa_deploy.server import PolicyService
    from sefa_sim.pusht import PushTEnv

    weak = (load_backend(ws / "flow", device="cpu", solver="euler", steps=1)
            if settings is not None and settings.weak else None)
    service = PolicyService(load_backend(ws / "distill", device="cpu"), execution=settings,
                            weak=weak, log=lambda s: None)
    env, actions, best = PushTEnv(), [], 0.0

    async def episode():
        nonlocal best
        session = service.new_session()
        await service.handle({"type": "reset", "seed": SEED}, session)
        obs = env.reset(SEED)
        for _ in range(STEPS):
            frame = {k: np.asarray(obs[k], np.float32) for k in ("keypoint", "state")}
            reply = await service.handle({"type": "step", "obs": frame}, session)
            actions.append(np.asarray(reply["action"], np.float64))
            obs, _, _, info = env.step(actions[-1])
            best = max(best, float(info["coverage"]))
    asyncio.run(episode())  # the worker is a daemon thread, idle once the episode ends
    return actions, best


@pytest.fixture
def one_torch_thread():
    """torch at one thread while the test runs (a CLI or another test may choose it): the
    server's worker thread must compute at the count of the thread that started it, which a
    new thread's matrix products do not on their own (MKL's count is per thread)."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.mark.parametrize("mode", list(MODES))
def test_eval_and_the_server_execute_the_same_actions(mode, deploy_workspace, monkeypatch,
                                                      one_torch_thread):
    from cli_inprocess import run_cli

    ws, (args, settings) = deploy_workspace, MODES[mode]
    recorded = []
    make = RecordingEnv
    monkeypatch.setattr("sefa_sim.pusht.PushTEnv", lambda: recorded.append(make()) or recorded[-1])
    r = run_cli("eval", "distill", "--env", "pusht", "--n-test", "1", "--max-steps", str(STEPS),
                "--start-seed", str(SEED), "-w", ws, "--json", "--force", *args)
    assert r.returncode == 0, r.stderr
    row = json.loads(r.stdout)[0]
    monkeypatch.undo()
    log = json.loads((ws / row["eval_log"]).read_text())
    assert log["execution_label"] == row["execution_label"]
    got, best = served_actions(ws, settings)
    eval_actions = recorded[0].actions
    assert len(eval_actions) == len(got) == STEPS
    np.testing.assert_array_equal(np.stack(eval_actions), np.stack(got))
    assert log["per_seed"][0]["max_coverage"] == best
    if mode != "receding-8":  # the other modes act differently from the default
        assert "execution" in json.loads((ws / row["cached_in"] / "result.json").read_text())["settings"]


def test_eval_stops_at_a_non_finite_action_with_one_line_and_writes_nothing(
        deploy_workspace, monkeypatch):
    """A policy whose chunk turns NaN mid-episode: Push-T would score the NaN target as reward
    0 and go on; `sefa eval` stops with one line naming the step and the episode, exit 1, and
    no result or log is kept (the sampler is patched: a loaded policy with finite weights does
    not answer NaN on its own)."""
    from cli_inprocess import run_cli
    import sefa_model.policy.execution as execution

    real = execution.policy_sampler

    def failing(*args, **kwargs):
        sample, calls = real(*args, **kwargs), []

        def nan_on_the_third(obs, noise, generator):
            calls.append(1)
            out = sample(obs, noise, generator)
            return out * np.nan if len(calls) == 3 else out
        return nan_on_the_third
    monkeypatch.setattr(execution, "policy_sampler", failing)
    ws = deploy_workspace
    before = sorted(p.relative_to(ws) for p in (ws / "evals").rglob("*")) if (ws / "evals").exists() else []
    r = run_cli("eval", "distill", "--env", "pusht", "--n-test", "1", "--max-steps", str(STEPS),
                "--start-seed", str(SEED), "-w", ws, "--execution", "receding",
                "--replan-every", "4")
    assert r.returncode == 1
    errors = [line for line in r.stderr.splitlines() if line.startswith("error:")]
    assert "Traceback" not in r.stderr and len(errors) == 1 and errors[0] == (
        "error: "
        "the policy predicted a non-finite action chunk (NaN or Inf) at step 8 of the episode "
        f"seeded {SEED}: nothing of it is executed"), r.stderr
    after = sorted(p.relative_to(ws) for p in (ws / "evals").rglob("*")) if (ws / "evals").exists() else []
    assert after == before


def test_n_samples_of_one_observation_encode_it_once_and_match_n_copies(deploy_workspace,
                                                                           deploy_exports):
    """A decision among N samples hands the sampler one observation and N noises: the policy
    encodes it once and gives the chunks N copies of it give (to float error), for the student
    and for a flow; an ONNX export (one observation per noise in its graph) repeats it."""
    import torch

    from sefa_deploy.backends import load_backend
    from sefa_model.policy.artifact import Policy

    ws = deploy_workspace
    for name, solver, steps in (("distill", None, None), ("flow", "euler", 2)):
        policy = Policy.load(ws / name, device="cpu")
        history = {k: np.random.default_rng(0).standard_normal(
            (1, policy.cfg.policy.n_obs_steps, *spec.frame_shape)).astype(np.float32) * 50 + 200
            for k, spec in policy.cfg.shape_meta.obs.items()}
        noise = torch.randn((4, policy.cfg.policy.horizon, 2), generator=torch.Generator().manual_seed(1))
        batches = []
        hook = policy.model.obs_encoder.register_forward_hook(
            lambda module, args, out: batches.append(out.shape[0]))
        one = policy.predict_action(history, noise=noise, solver=solver, steps=steps).action_pred
        copies = policy.predict_action({k: np.repeat(v, 4, axis=0) for k, v in history.items()},
                                       noise=noise, solver=solver, steps=steps).action_pred
        hook.remove()
        assert batches == [1, 4]  # encoded once for the 4 noises; 4 copies, 4 times
        assert one.shape == (4, policy.cfg.policy.horizon, 2)
        torch.testing.assert_close(one, copies, rtol=1e-5, atol=1e-4)
        with pytest.raises(ValueError, match="2 observations for 4 noises"):
            policy.predict_action({k: np.repeat(v, 2, axis=0) for k, v in history.items()},
                                  noise=noise)
    pytest.importorskip("onnxruntime", reason="the deploy extra is not installed")
    export = load_backend(deploy_exports("one-step", "onnx"), device="cpu")
    student = Policy.load(ws / "distill", device="cpu")
    history = {k: np.zeros((1, *spec["shape"]), np.float32) for k, spec in export.metadata["obs"].items()}
    noise = np.random.default_rng(2).standard_normal((3, 16, 2)).astype(np.float32)
    _, chunks = export(history, noise)
    want = student.predict_action(history, noise=torch.from_numpy(noise)).action_pred.numpy()
    assert chunks.shape == (3, 16, 2)
    np.testing.assert_allclose(chunks, want, rtol=1e-4, atol=1e-3)
