"""The server's `step` path (sefa_model/policy/execution.py's Executor per connection), in
process, on a fake policy whose chunks are known: what is sent, when it predicts, the step
times reported, a non-finite action never sent, the noise a step may carry, a reset's seed,
and bad option values refused naming the option. The execution math itself is tested in
tests/sefa_model_tests/test_execution.py."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from sefa_data.errors import ConfigError
from sefa_model.policy.execution import ExecutionSettings, Executor
from sefa_deploy.server import PolicyOutputError, PolicyService, RequestError

DA, NA = 1, 4  # action dim, n_action_steps of the fake policy


def test_serve_option_ranges():
    from sefa_pipelines.options import execution_option

    with pytest.raises(ConfigError, match="--ensemble-k"):
        execution_option("ensemble", ensemble_k=-0.1)
    with pytest.raises(ConfigError, match="--ensemble-k"):
        execution_option("ensemble", ensemble_k=float("nan"))
    with pytest.raises(ConfigError, match="--replan-every"):
        execution_option(None, replan_every=0)
    assert execution_option(None) is None


# ---- the server's step path, in process, on a fake policy

class FakePolicy:
    """Chunk k (k-th call) executes 100 k + [0, 1, 2, 3] (action_pred from index n_obs_steps
    - 1 = 1, the current step, on); sample j of a batch adds 10 j."""
    name, device = "fake", "cpu"

    def __init__(self, n_obs_steps: int = 2):
        self.calls, self.noises = 0, []
        self.metadata = {"n_obs_steps": n_obs_steps, "n_action_steps": NA, "action_dim": DA,
                         "horizon": 8, "noise": {"shape": [8, DA]},
                         "obs": {"state": {"shape": [n_obs_steps, 2], "dtype": "float32"}}}

    def __call__(self, obs, noise, generator=None):
        self.noises.append(noise.copy())
        n = noise.shape[0]
        base = 100.0 * self.calls
        self.calls += 1
        pred = np.zeros((n, 8, DA), np.float32)
        start = self.metadata["n_obs_steps"] - 1
        pred[:, start:start + NA, 0] = base + 10.0 * np.arange(n)[:, None] + np.arange(NA)
        return pred[:, start:start + NA].copy(), pred


def step_all(service: PolicyService, n: int) -> list[dict]:
    async def go():
        session = service.new_session()
        frame = {"state": np.zeros(2, np.float32)}
        return [await service.handle({"type": "step", "obs": frame}, session) for _ in range(n)]
    return asyncio.run(go())


def test_the_server_ensembles_when_asked_and_reports_step_times():
    policy = FakePolicy()
    service = PolicyService(policy, execution=ExecutionSettings("ensemble", ensemble_k=0.0),
                            log=lambda s: None)
    replies = step_all(service, 3)
    assert policy.calls == 3 and [r["replanned"] for r in replies] == [True] * 3
    # step 1: mean(1, 100); step 2: mean(2, 101, 200)
    assert [r["action"].tolist() for r in replies] == [[0.0], [50.5], [101.0]]
    assert [r["queued"] for r in replies] == [1, 2, 3]
    assert all(r["step_ms"] > 0 for r in replies)
    stats = service.step_stats()
    assert stats["steps"] == 3 and stats["execution"] == "ensemble"
    assert stats["step_jitter_ms"] == pytest.approx(stats["step_ms_p99"] - stats["step_ms_p50"])


def test_the_server_default_is_receding_horizon_over_the_whole_chunk():
    policy = FakePolicy()
    replies = step_all(PolicyService(policy, log=lambda s: None), 5)
    assert policy.calls == 2 and [r["replanned"] for r in replies] == [True, False, False, False, True]
    assert [r["action"].tolist() for r in replies] == [[0], [1], [2], [3], [100]]
    assert [r["queued"] for r in replies] == [3, 2, 1, 0, 3]


def test_a_non_finite_ensembled_action_is_never_sent(monkeypatch):
    # finite chunks average to finite actions (the mean is taken in float64), so the fault is
    # injected where the ensembling answers: the server's last check must still catch it
    from sefa_model.policy.execution import Ensembler

    monkeypatch.setattr(Ensembler, "action", lambda self, t: (np.array([np.nan], np.float32), 1))
    service = PolicyService(FakePolicy(), execution=ExecutionSettings("ensemble"),
                            log=lambda s: None)
    with pytest.raises(PolicyOutputError, match="not finite"):
        step_all(service, 1)


def test_a_step_that_times_out_keeps_the_connection_busy_until_its_prediction_ends():
    """The first prediction outlives --request-timeout: its step is answered with the timeout,
    and until the prediction ends the connection's next step and reset are refused (they would
    race it on the executor); then the steps go on from the plan, the timed-out step counted."""
    import threading

    started, release = threading.Event(), threading.Event()

    class Held(FakePolicy):
        def __call__(self, obs, noise, generator=None):
            if self.calls == 0:
                started.set()
                assert release.wait(30)
            return super().__call__(obs, noise, generator)

    policy = Held()
    # the worker starts the held call at once, well within the timeout; the call then outlives it
    service = PolicyService(policy, request_timeout_s=0.5, log=lambda s: None)

    async def go():
        session = service.new_session()
        step = {"type": "step", "obs": {"state": np.zeros(2, np.float32)}}
        with pytest.raises(RequestError, match="no answer within 0.5 s"):
            await service.handle(step, session)
        assert started.is_set()  # it timed out running, not waiting
        for request in (step, {"type": "reset"}):
            with pytest.raises(RequestError, match="previous prediction is still running"):
                await service.handle(request, session)
        release.set()
        for _ in range(3000):  # the worker clears it as the prediction ends
            if not session.busy:
                break
            await asyncio.sleep(0.01)
        replies = [await service.handle(step, session) for _ in range(4)]
        await service.handle({"type": "reset"}, session)
        return replies

    replies = asyncio.run(go())
    assert [r["action"].tolist() for r in replies] == [[1], [2], [3], [100]]
    assert [r["replanned"] for r in replies] == [False, False, False, True]
    assert policy.calls == 2


def test_the_ready_line_says_where_the_served_execution_came_from():
    from sefa_cli.deploy import _execution_origin

    given = ExecutionSettings("receding", 2)
    recorded = {"execution": given.to_json()}
    assert _execution_origin(given, None, recorded) == ""  # typed as options
    assert _execution_origin(given, "sefa.yaml", recorded) == " (from sefa.yaml)"
    assert _execution_origin(None, None, {**recorded, "execution_source": "given"}) == (
        " (given at export)")
    assert _execution_origin(None, None, {**recorded, "execution_source": "chosen"}) == (
        " (chosen for this policy)")
    assert _execution_origin(None, None, {"execution": None}) == ""


def test_the_service_refuses_a_replan_every_longer_than_the_chunk():
    with pytest.raises(ConfigError, match="--replan-every"):
        PolicyService(FakePolicy(), execution=ExecutionSettings("receding", NA + 1))


def test_serve_names_sefa_yaml_for_a_bad_execution_read_from_it():
    from sefa_deploy.server import served_execution

    meta = FakePolicy().metadata
    with pytest.raises(ConfigError, match=r"^sefa.yaml: execution.replan_every: 9 is outside 1..4"):
        served_execution(meta, ExecutionSettings("receding", 9), "sefa.yaml")
    with pytest.raises(ConfigError, match=r"^--replan-every: 9 is outside 1..4"):
        served_execution(meta, ExecutionSettings("receding", 9))


def test_the_server_runs_the_execution_recorded_with_the_policy():
    policy = FakePolicy()
    policy.metadata["execution"] = ExecutionSettings("receding", 2).to_json()
    replies = step_all(PolicyService(policy, log=lambda s: None), 3)
    assert [r["action"].tolist() for r in replies] == [[0], [1], [100]]
    # given settings win over the recorded ones
    replies = step_all(PolicyService(FakePolicy(), execution=ExecutionSettings("receding", 1),
                                     log=lambda s: None), 2)
    assert [r["action"].tolist() for r in replies] == [[0], [100]]


def test_a_coherent_server_draws_its_samples_in_one_call_and_takes_their_noise():
    policy = FakePolicy()
    service = PolicyService(policy, execution=ExecutionSettings("coherent", samples=3),
                            log=lambda s: None)
    replies = step_all(service, 2)
    assert policy.calls == 2 and [n.shape for n in policy.noises] == [(3, 8, DA)] * 2
    # step 1: the previous plan says 1, 2, 3 next; the samples 100 + 10 j: sample 0 nearest
    assert [r["action"].tolist() for r in replies] == [[0], [100]]

    async def with_noise():
        service = PolicyService(policy, execution=ExecutionSettings("coherent", samples=3),
                                log=lambda s: None)
        session = service.new_session()
        frame = {"state": np.zeros(2, np.float32)}
        noise = np.full((3, 8, DA), 0.5, np.float32)
        await service.handle({"type": "step", "obs": frame, "noise": noise}, session)
        with pytest.raises(RequestError, match=r"noise: a step takes \(3, 8, 1\)"):
            await service.handle({"type": "step", "obs": frame, "noise": noise[0]},
                                 service.new_session())
    asyncio.run(with_noise())
    np.testing.assert_array_equal(policy.noises[-1], np.full((3, 8, DA), 0.5, np.float32))


def test_a_reset_seed_gives_the_noise_an_executor_seeded_alike_draws():
    policy, seen = FakePolicy(), []

    async def go():
        service = PolicyService(policy, log=lambda s: None, seed=3)
        session = service.new_session()
        frame = {"state": np.zeros(2, np.float32)}
        await service.handle({"type": "reset", "seed": 11}, session)
        await service.handle({"type": "step", "obs": frame}, session)
        with pytest.raises(RequestError, match="seed must be an integer"):
            await service.handle({"type": "reset", "seed": -1}, session)
    asyncio.run(go())
    ex = Executor(ExecutionSettings("receding"), lambda o, n, g: seen.append(n) or
                  np.zeros((1, 8, DA), np.float32), service_shape(policy), seed=11)
    ex.action({"state": np.zeros(2, np.float32)})
    np.testing.assert_array_equal(policy.noises[0], seen[0])


def service_shape(policy):
    from sefa_model.policy.execution import ChunkShape

    return ChunkShape.of(policy.metadata)
