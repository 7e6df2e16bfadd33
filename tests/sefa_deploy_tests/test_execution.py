"""Issue 24, point 2: chunk execution for `step` requests. The weighting math on hand-made
chunks with exact expected arrays (ACT's temporal ensembling: w_i = exp(-k i), i = 0 the
oldest), receding horizon with replan_every, and the server's `step` path with each mode on a
fake policy whose chunks are known: what is sent, when it predicts, the step times reported,
a non-finite ensemble never sent, and bad option values refused naming the option."""

from __future__ import annotations

import asyncio
import math

import numpy as np
import pytest

from sefa_deploy.execution import Ensembler, Execution, check_execution, ensemble_weights
from sefa_deploy.server import PolicyOutputError, PolicyService

DA, NA = 1, 4  # action dim, n_action_steps of the fake policy


def test_ensemble_weights_are_acts_normalized_exponential_oldest_first():
    w = ensemble_weights(3, 0.5)
    raw = np.array([1.0, math.exp(-0.5), math.exp(-1.0)])
    np.testing.assert_allclose(w, raw / raw.sum(), rtol=1e-12)
    np.testing.assert_allclose(ensemble_weights(4, 0.0), [0.25] * 4)  # k = 0: the plain mean
    assert ensemble_weights(1, 0.01).tolist() == [1.0]


def test_ensembler_averages_every_prediction_of_the_step_with_the_oldest_weighted_most():
    e = Ensembler(k=math.log(2))  # weights 1, 1/2, 1/4 before normalizing
    e.add(0, np.array([[0.0], [10.0], [20.0], [30.0]]))
    a, n = e.action(0)
    assert n == 1 and a.tolist() == [0.0]
    e.add(1, np.array([[11.0], [21.0], [31.0], [41.0]]))
    a, n = e.action(1)  # (10 * 1 + 11 * 1/2) / 1.5
    assert n == 2 and a == pytest.approx([(10 + 11 / 2) / 1.5])
    e.add(2, np.array([[22.0], [32.0], [42.0], [52.0]]))
    a, n = e.action(2)  # (20 + 21/2 + 22/4) / 1.75
    assert n == 3 and a == pytest.approx([(20 + 21 / 2 + 22 / 4) / 1.75])
    a, n = e.action(4)  # chunk 0 ends at step 3: dropped, chunk 1 is now the oldest
    assert n == 2 and a == pytest.approx([(41 + 42 / 2) / 1.5]) and len(e.chunks) == 2
    with pytest.raises(ValueError, match="no prediction covers step 6"):
        e.action(6)


def test_ensembler_keeps_each_action_dimension_apart():
    e = Ensembler(k=0.0)
    e.add(0, np.array([[1.0, -1.0], [2.0, -2.0]]))
    e.add(1, np.array([[4.0, -4.0], [5.0, -5.0]]))
    a, _ = e.action(1)
    assert a.dtype == np.float32 and a.tolist() == [3.0, -3.0]


def run_steps(ex: Execution, chunks, n: int) -> tuple[list, list]:
    """Drives an Execution as the server does; chunk k is the k-th prediction."""
    it, actions, plans = iter(chunks), [], []
    for _ in range(n):
        if ex.due():
            plans.append(ex.t)
            ex.add(next(it))
        actions.append(ex.next()[0].tolist())
    return actions, plans


def chunk(base: float) -> np.ndarray:
    return (base + np.arange(NA, dtype=np.float32))[:, None]


def test_receding_executes_replan_every_actions_then_predicts_again():
    actions, plans = run_steps(Execution("receding", NA), [chunk(0), chunk(100)], 6)
    assert plans == [0, 4] and actions == [[0], [1], [2], [3], [100], [101]]
    actions, plans = run_steps(Execution("receding", 2), [chunk(0), chunk(100), chunk(200)], 6)
    assert plans == [0, 2, 4] and actions == [[0], [1], [100], [101], [200], [201]]


def test_ensemble_predicts_every_replan_every_steps_and_averages_what_covers_the_step():
    ex = Execution("ensemble", 2, k=0.0)
    actions, plans = run_steps(ex, [chunk(0), chunk(100), chunk(200)], 5)
    # step 2: chunk 0's [2] and chunk 1's [0]; step 3: 3 and 101; step 4: 102 and 200
    assert plans == [0, 2, 4] and actions == [[0], [1], [51], [52], [151]]
    ex.reset()
    assert ex.due() and ex.t == 0 and not ex.ensembler.chunks


def test_bad_execution_options_are_refused_naming_the_option():
    with pytest.raises(ValueError, match="--replan-every: 5 is outside 1..4"):
        check_execution("ensemble", 5, 0.01, NA)
    with pytest.raises(ValueError, match="--execution: 'act'"):
        check_execution("act", None, 0.01, NA)
    with pytest.raises(ValueError, match="--ensemble-k: nan"):
        check_execution("ensemble", None, float("nan"), NA)
    assert check_execution("receding", None, 0.01, NA) == NA
    assert check_execution("ensemble", None, 0.01, NA) == 1


def test_serve_option_ranges():
    from sefa_pipelines.options import check_options
    from sefa_data.errors import ConfigError

    with pytest.raises(ConfigError, match="--ensemble-k"):
        check_options("serve", {"--ensemble-k": -0.1})
    with pytest.raises(ConfigError, match="--ensemble-k"):
        check_options("serve", {"--ensemble-k": float("nan")})
    with pytest.raises(ConfigError, match="--replan-every"):
        check_options("serve", {"--replan-every": 0})


# ---- the server's step path, in process, on a fake policy

class FakePolicy:
    """Chunk k (k-th call) is 100 k + [0, 1, 2, 3]; `poison` makes the values of call k NaN at
    the step index given (the chunk itself then fails the server's output check)."""
    name, device = "fake", "cpu"

    def __init__(self, n_obs_steps: int = 2):
        self.calls = 0
        self.metadata = {"n_obs_steps": n_obs_steps, "n_action_steps": NA, "action_dim": DA,
                         "noise": {"shape": [8, DA]},
                         "obs": {"state": {"shape": [n_obs_steps, 2], "dtype": "float32"}}}

    def __call__(self, obs, noise):
        base = 100.0 * self.calls
        self.calls += 1
        pred = np.zeros((1, 8, DA), np.float32)
        pred[0, :NA, 0] = base + np.arange(NA)
        return pred[:, :NA].copy(), pred


def step_all(service: PolicyService, n: int) -> list[dict]:
    async def go():
        session = service.new_session()
        frame = {"state": np.zeros(2, np.float32)}
        return [await service.handle({"type": "step", "obs": frame}, session) for _ in range(n)]
    return asyncio.run(go())


def test_the_server_ensembles_when_asked_and_reports_step_times():
    policy = FakePolicy()
    service = PolicyService(policy, execution="ensemble", ensemble_k=0.0, log=lambda s: None)
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
    monkeypatch.setattr(Ensembler, "action", lambda self, t: (np.array([np.nan], np.float32), 1))
    service = PolicyService(FakePolicy(), execution="ensemble", log=lambda s: None)
    with pytest.raises(PolicyOutputError, match="not finite"):
        step_all(service, 1)


def test_the_service_refuses_a_replan_every_longer_than_the_chunk():
    with pytest.raises(ValueError, match="--replan-every"):
        PolicyService(FakePolicy(), execution="receding", replan_every=NA + 1)


BAD_OPTIONS = [
    (["--execution", "act"], "--execution: not one of receding, ensemble: 'act'"),
    (["--ensemble-k", "-0.5"], "--ensemble-k: -0.5 is too small (valid: a finite number >= 0)"),
    (["--ensemble-k", "nan"], "--ensemble-k: nan is not a finite number"),
    (["--replan-every", "0"], "--replan-every: 0 is too small"),
]


@pytest.mark.parametrize("args,line", BAD_OPTIONS, ids=[" ".join(a) for a, _ in BAD_OPTIONS])
def test_bad_execution_options_are_one_line_before_any_work(args, line, monkeypatch, capsys):
    """The policy path does not exist: an option checked only after loading would say so."""
    from sefa_cli.main import main

    monkeypatch.setattr("sys.argv", ["sefa", "serve", "no-such-policy", *args])
    with pytest.raises(SystemExit) as e:
        main()
    err = capsys.readouterr().err
    assert e.value.code == 1 and err.count("\n") == 1 and "Traceback" not in err
    assert err.startswith(f"error: {line}")
