"""ODE solvers against known answers: scipy's RK45, matrix exponentials, convergence orders."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.linalg
import torch
from scipy.integrate import solve_ivp

from sefa_model.flow.solvers import (ADAPTIVE, METHODS, SolveResult, dop853_ps, euler, midpoint, rk4, rk45,
                                rk45_ps, solve)

F64 = torch.float64


class Counted:
    """Wraps a velocity field, counts its calls and checks the ``t`` contract on every call
    (one shared t unless ``per_sample``); ``rows`` records the batch size of every call."""

    def __init__(self, f, per_sample: bool = False):
        self.f = f
        self.per_sample = per_sample
        self.calls = 0
        self.rows: list[int] = []

    def __call__(self, x: torch.Tensor, t: torch.Tensor, *cond: torch.Tensor) -> torch.Tensor:
        assert t.shape == (x.shape[0],)
        assert t.dtype == x.dtype and t.device == x.device
        assert self.per_sample or torch.all(t == t[0])
        self.calls += 1
        self.rows.append(x.shape[0])
        return self.f(x, t, *cond)


def linear_field(A: torch.Tensor):
    """dx/dt = A_b x_b for each batch element b; A: (B, d, d)."""
    return lambda x, t: torch.einsum("bij,bj->bi", A, x)


def cubic_field(x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """dx/dt = -x^3 + sin(t): nonlinear and time-dependent; x: (B, d)."""
    return -x**3 + torch.sin(t)[:, None]


def rotating_stable(B: int, d: int, gen: torch.Generator) -> torch.Tensor:
    """(B, d, d): a strong rotation (skew part) plus damping plus a small random perturbation."""
    S = torch.randn(B, d, d, dtype=F64, generator=gen)
    P = torch.randn(B, d, d, dtype=F64, generator=gen)
    return 2 * (S - S.transpose(1, 2)) - 0.3 * torch.eye(d, dtype=F64) + 0.2 * P


def scipy_rk45(f, x0: torch.Tensor, t0: float, t1: float, tol: float, **kw):
    """solve_ivp RK45 on the flattened batch, evaluating the very same torch field."""
    shape = x0.shape

    def fun(t, y):
        x = torch.from_numpy(y).view(shape)
        return f(x, torch.full((shape[0],), t, dtype=F64)).reshape(-1).numpy()

    sol = solve_ivp(fun, (t0, t1), x0.reshape(-1).numpy(), method="RK45", rtol=tol, atol=tol, **kw)
    assert sol.success
    return sol.y[:, -1].reshape(shape), sol


# ----------------------------------------------------------------------------- rk45 vs scipy


@pytest.mark.parametrize("d", [2, 3, 4])
@pytest.mark.parametrize("tol", [1e-6, 1e-8])
def test_rk45_linear_matches_scipy_and_expm(d, tol):
    gen = torch.Generator().manual_seed(d)
    B = 8
    A = rotating_stable(B, d, gen)
    x0 = torch.randn(B, d, dtype=F64, generator=gen)
    f = Counted(linear_field(A))

    res = rk45(f, x0, 0.0, 1.0, rtol=tol, atol=tol)
    ref, sol = scipy_rk45(linear_field(A), x0, 0.0, 1.0, tol)
    exact = np.stack([scipy.linalg.expm(A[b].numpy()) @ x0[b].numpy() for b in range(B)])

    # Same algorithm, same float64 arithmetic: scipy is matched to rounding, not to tolerance
    # (measured ~1e-15), and the step-size decisions are the same, hence the same NFE.
    assert np.abs(res.x.numpy() - ref).max() < 1e-12
    assert res.nfe == sol.nfev == f.calls
    # Against the exact solution the global error is a few times the tolerance (measured
    # <= 2e-5 at 1e-6 and <= 2e-7 at 1e-8 over these problems).
    assert np.abs(res.x.numpy() - exact).max() < 100 * tol


# Backwards in time -x^3 is explosive (blow-up after 1 / (2 x0^2)), hence the smaller start.
@pytest.mark.parametrize("t0, t1, scale", [(1e-3, 2.0, 2.0), (0.0, 1.0, 2.0), (1.0, 0.8, 0.25)])
def test_rk45_nonlinear_matches_scipy(t0, t1, scale):
    gen = torch.Generator().manual_seed(1)
    x0 = scale * torch.randn(16, 3, dtype=F64, generator=gen)
    f = Counted(cubic_field)

    res = rk45(f, x0, t0, t1, rtol=1e-6, atol=1e-6)
    ref, sol = scipy_rk45(cubic_field, x0, t0, t1, 1e-6)

    assert np.abs(res.x.numpy() - ref).max() < 1e-4  # stated bound; measured ~1e-15
    assert abs(res.nfe - sol.nfev) <= 0.3 * sol.nfev  # stated bound; measured equal
    assert res.nfe == f.calls == 2 + 6 * (res.steps + res.rejected)


def test_rk45_rejections_follow_scipy():
    """A deliberately too large first step forces rejections; scipy must reject the same way."""
    gen = torch.Generator().manual_seed(2)
    x0 = 3 * torch.randn(4, 2, dtype=F64, generator=gen)
    f = Counted(cubic_field)

    res = rk45(f, x0, 0.0, 3.0, rtol=1e-7, atol=1e-7, first_step=1.0)
    ref, sol = scipy_rk45(cubic_field, x0, 0.0, 3.0, 1e-7, first_step=1.0)

    assert res.rejected > 0
    assert np.abs(res.x.numpy() - ref).max() < 1e-12
    # With first_step given there is no probe evaluation: 1 + 6 per attempt.
    assert res.nfe == f.calls == sol.nfev == 1 + 6 * (res.steps + res.rejected)


def test_rk45_lands_exactly_on_t1():
    seen: list[float] = []

    def f(x, t):
        seen.append(t[0].item())
        return torch.ones_like(x)

    x0 = torch.zeros(3, 2, dtype=F64)
    res = rk45(f, x0, 1e-3, 0.7)
    assert seen[-1] == 0.7
    assert max(seen) <= 0.7 and min(seen) >= 1e-3  # f is never evaluated outside [t0, t1]
    torch.testing.assert_close(res.x, torch.full_like(x0, 0.7 - 1e-3), rtol=0, atol=1e-14)


def test_rk45_float32_close_to_float64():
    gen = torch.Generator().manual_seed(3)
    x0 = torch.randn(32, 5, dtype=F64, generator=gen)
    r64 = rk45(cubic_field, x0, 0.0, 1.0, rtol=1e-5, atol=1e-5)
    r32 = rk45(Counted(cubic_field), x0.float(), 0.0, 1.0, rtol=1e-5, atol=1e-5)
    assert r32.x.dtype == torch.float32 and r32.x.device == x0.device
    assert (r32.x.double() - r64.x).abs().max() < 1e-4


def test_rk45_zero_interval_costs_nothing():
    x0 = torch.randn(2, 3)
    res = rk45(Counted(cubic_field), x0, 0.5, 0.5)
    assert res == SolveResult(x=x0, nfe=0, steps=0, rejected=0)


def test_rk45_max_steps_exceeded():
    x0 = torch.randn(4, 2, dtype=F64)
    with pytest.raises(RuntimeError, match="max_steps=3 exceeded"):
        rk45(cubic_field, x0, 0.0, 10.0, rtol=1e-10, atol=1e-10, max_steps=3)


def test_rk45_step_underflow_on_non_finite_field():
    def f(x, t):
        return torch.where(t[:, None] > 0.5, torch.nan, 1.0) * torch.ones_like(x)

    with pytest.raises(RuntimeError, match="underflow"):
        rk45(f, torch.zeros(2, 2, dtype=F64), 0.0, 1.0)


@pytest.mark.parametrize("kw", [dict(first_step=0.0), dict(first_step=2.0), dict(rtol=-1.0),
                                dict(rtol=0.0, atol=0.0)])
def test_rk45_bad_arguments(kw):
    with pytest.raises(ValueError):
        rk45(cubic_field, torch.zeros(2, 2), 0.0, 1.0, **kw)


# ----------------------------------------------------------------------------- fixed step


@pytest.mark.parametrize("method, order", [(euler, 1), (midpoint, 2), (rk4, 4)])
def test_fixed_step_order_of_convergence(method, order):
    """dx/dt = x, x(0) = 1: halving the step divides the error at t=1 by ~2**order."""
    x0 = torch.ones(1, 1, dtype=F64)
    f = lambda x, t: x  # noqa: E731
    n = 32 if order < 4 else 8  # rk4 at n=32 would hit float64 rounding before the halving
    errors = [abs(method(f, x0, 0.0, 1.0, k).x.item() - math.e) for k in (n, 2 * n)]
    ratio = errors[0] / errors[1]
    assert abs(math.log2(ratio) - order) < 0.1, ratio


@pytest.mark.parametrize("method", [euler, midpoint, rk4])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_one_step_exact_for_constant_velocity(method, dtype):
    gen = torch.Generator().manual_seed(4)
    x0 = torch.randn(5, 3, 2, generator=gen).to(dtype)
    v = torch.randn(5, 3, 2, generator=gen).to(dtype)
    f = Counted(lambda x, t: v)
    res = method(f, x0, 1e-3, 1.0, 1)
    assert res.x.dtype == dtype and res.x.device == x0.device
    expected = x0 + (1.0 - 1e-3) * v
    if method is euler:
        assert torch.equal(res.x, expected)  # bit-exact: the one-step sampler relies on it
    else:  # the stage weights sum to 1 only up to rounding
        torch.testing.assert_close(res.x, expected, rtol=0, atol=4 * torch.finfo(dtype).eps)


@pytest.mark.parametrize("method, exact_degree", [(euler, 0), (midpoint, 1), (rk4, 3)])
def test_fixed_step_exact_for_polynomials_in_t(method, exact_degree):
    """dx/dt = t^k is a quadrature; each rule is exact up to its degree — checks the stage times."""
    x0 = torch.zeros(2, 1, dtype=F64)
    k = exact_degree
    res = method(lambda x, t: (t**k)[:, None].expand_as(x), x0, 0.5, 2.0, 3)
    torch.testing.assert_close(res.x, torch.full_like(x0, (2.0 ** (k + 1) - 0.5 ** (k + 1)) / (k + 1)))


@pytest.mark.parametrize("name, per_step", [("euler", 1), ("midpoint", 2), ("rk4", 4)])
@pytest.mark.parametrize("n", [1, 7])
def test_fixed_step_nfe(name, per_step, n):
    f = Counted(cubic_field)
    res = solve(f, torch.randn(3, 2), name, steps=n)
    assert res.nfe == f.calls == per_step * n
    assert res.steps == n and res.rejected == 0


def test_fixed_step_runs_backwards_in_time():
    x0 = torch.ones(1, 1, dtype=F64)
    res = rk4(lambda x, t: x, x0, 1.0, 0.0, 20)
    assert abs(res.x.item() - math.exp(-1)) < 1e-7


@pytest.mark.parametrize("method", ["rk45-ps", "dop853-ps"])
def test_a_sample_with_zero_error_keeps_a_finite_gradient(method):
    """A sample whose error estimate is exactly 0 (here: it starts at the field's fixed point)
    grows its step by the maximum factor; the gradient does not pass through that decision
    (0 ** -1/5 would make it NaN), so d x1 / d x0 is the flow's, exp(w), for every sample."""
    x0 = torch.zeros(3, 2)
    x0[1:] = torch.tensor([[0.3, -1.2], [2.0, 0.7]])
    x0.requires_grad_(True)
    res = solve(lambda x, t: 0.5 * x, x0, method)
    (gx,) = torch.autograd.grad(res.x.sum(), x0)
    torch.testing.assert_close(gx, torch.full_like(x0, math.exp(0.5)), rtol=1e-5, atol=0)


def test_gradients_flow_unless_the_caller_disables_them():
    x0 = torch.randn(4, 2, requires_grad=True)
    w = torch.tensor(0.5, requires_grad=True)
    for method, kw in [("rk4", dict(steps=4)), ("rk45", {}), ("rk45-ps", {}), ("dop853-ps", {})]:
        res = solve(lambda x, t: w * x, x0, method, **kw)
        assert res.x.requires_grad
        (gx,) = torch.autograd.grad(res.x.sum(), x0)
        torch.testing.assert_close(gx, torch.full_like(x0, math.exp(0.5)), rtol=1e-4, atol=0)
    with torch.no_grad():
        assert not solve(lambda x, t: w * x, x0, "euler", steps=2).x.requires_grad


# ----------------------------------------------------------------------------- dispatch


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_solve_dispatches_every_method(dtype):
    x0 = torch.ones(2, 1, dtype=dtype)
    for method in METHODS:
        kw = {} if method in ADAPTIVE else dict(steps=64)
        res = solve(lambda x, t: x, x0, method, **kw)
        assert res.x.dtype == dtype
        assert abs(res.x[0].item() - math.e) < 0.03  # euler at 64 steps is the loosest


def test_solve_unknown_method_names_the_valid_ones():
    with pytest.raises(ValueError, match="euler, midpoint, rk4, rk45"):
        solve(cubic_field, torch.zeros(1, 1), "heun", steps=2)


@pytest.mark.parametrize("steps", [None, 0])
def test_solve_fixed_step_needs_steps(steps):
    with pytest.raises(ValueError, match="steps >= 1"):
        solve(cubic_field, torch.zeros(1, 1), "euler", steps=steps)


@pytest.mark.parametrize("method", ADAPTIVE)
def test_solve_adaptive_refuses_steps(method):
    with pytest.raises(ValueError, match="adaptive"):
        solve(cubic_field, torch.zeros(1, 1), method, steps=4)


# ----------------------------------------------------------------------------- per-sample control

PER_SAMPLE = [(rk45_ps, "RK45", 6), (dop853_ps, "DOP853", 12)]


def scipy_each(f, x0: torch.Tensor, t0: float, t1: float, tol: float, method: str, cond=None, **kw):
    """solve_ivp on every sample ALONE (the per-sample methods' definition): (x1, nfev per sample)."""
    xs, nfev = [], []
    for b in range(x0.shape[0]):
        shape = (1,) + tuple(x0.shape[1:])
        extra = () if cond is None else (cond[b:b + 1],)

        def fun(t, y):
            x = torch.from_numpy(y).view(shape)
            return f(x, torch.full((1,), t, dtype=F64), *extra).reshape(-1).numpy()

        sol = solve_ivp(fun, (t0, t1), x0[b].reshape(-1).numpy(), method=method, rtol=tol, atol=tol, **kw)
        assert sol.success
        xs.append(sol.y[:, -1].reshape(x0.shape[1:]))
        nfev.append(sol.nfev)
    return np.stack(xs), np.array(nfev)


def test_dop853_tableau_is_scipys():
    from scipy.integrate._ivp import dop853_coefficients as ref

    from sefa_model.flow import solvers

    n = ref.N_STAGES
    a = np.zeros((n, n))
    for i, row in enumerate(solvers._A853):
        a[i, :len(row)] = row
    assert np.array_equal(a, ref.A[:n, :n])
    assert np.array_equal(solvers._C853, ref.C[:n])
    assert np.array_equal(solvers._B853, ref.B)
    assert np.array_equal(solvers._E5_853, ref.E5[:n]) and ref.E5[n] == 0
    # E3 is B minus three corrections; computed here as in scipy, so equal to rounding
    np.testing.assert_allclose(solvers._E3_853, ref.E3[:n], rtol=0, atol=1e-16)
    assert ref.E3[n] == 0


@pytest.mark.parametrize("solver, scipy_method, per_attempt", PER_SAMPLE)
@pytest.mark.parametrize("tol", [1e-5, 1e-8])
def test_per_sample_is_scipy_on_each_sample_alone(solver, scipy_method, per_attempt, tol):
    """Linear problems of very different speeds: every sample takes exactly the steps that
    solve_ivp takes on it alone (same result to rounding, same nfev)."""
    gen = torch.Generator().manual_seed(5)
    B, d = 6, 3
    A = rotating_stable(B, d, gen) * torch.tensor([0.1, 0.5, 1, 2, 4, 8], dtype=F64)[:, None, None]
    x0 = torch.randn(B, d, dtype=F64, generator=gen)
    f = Counted(linear_field(A), per_sample=True)
    res = solver(lambda x, t, a: torch.einsum("bij,bj->bi", a, x), x0, 0.0, 1.0, rtol=tol, atol=tol,
                 cond=A)
    ref, nfev = scipy_each(lambda x, t, a: torch.einsum("bij,bj->bi", a, x), x0, 0.0, 1.0, tol,
                           scipy_method, cond=A)
    assert np.abs(res.x.numpy() - ref).max() < 1e-12  # measured ~1e-15
    assert np.array_equal(res.sample_nfe.numpy(), nfev)
    # every sample is in every call until it finishes; the work is the rows evaluated
    assert res.nfe == nfev.max() and res.sample_evals == nfev.sum()
    assert res.steps + res.rejected == (nfev - 2).sum() // per_attempt
    exact = np.stack([scipy.linalg.expm(A[b].numpy()) @ x0[b].numpy() for b in range(B)])
    assert np.abs(res.x.numpy() - exact).max() < 100 * tol
    del f


@pytest.mark.parametrize("solver, scipy_method, per_attempt", PER_SAMPLE)
@pytest.mark.parametrize("t0, t1, scale", [(1e-3, 2.0, 2.0), (1.0, 0.8, 0.25)])
def test_per_sample_nonlinear_matches_scipy(solver, scipy_method, per_attempt, t0, t1, scale):
    gen = torch.Generator().manual_seed(1)
    x0 = scale * torch.randn(8, 3, dtype=F64, generator=gen)
    f = Counted(cubic_field, per_sample=True)
    res = solver(f, x0, t0, t1, rtol=1e-6, atol=1e-6)
    ref, nfev = scipy_each(cubic_field, x0, t0, t1, 1e-6, scipy_method)
    assert np.abs(res.x.numpy() - ref).max() < 1e-12
    assert np.array_equal(res.sample_nfe.numpy(), nfev)
    assert res.nfe == f.calls and res.sample_evals == sum(f.rows)
    assert np.all((res.sample_nfe.numpy() - 2) % per_attempt == 0)


@pytest.mark.parametrize("solver, scipy_method, per_attempt", PER_SAMPLE)
def test_per_sample_rejections_follow_scipy(solver, scipy_method, per_attempt):
    gen = torch.Generator().manual_seed(2)
    x0 = 3 * torch.randn(4, 2, dtype=F64, generator=gen)
    res = solver(cubic_field, x0, 0.0, 3.0, rtol=1e-7, atol=1e-7, first_step=1.0)
    ref, nfev = scipy_each(cubic_field, x0, 0.0, 3.0, 1e-7, scipy_method, first_step=1.0)
    assert res.rejected > 0
    assert np.abs(res.x.numpy() - ref).max() < 1e-12
    assert np.array_equal(res.sample_nfe.numpy(), nfev)  # no probe evaluation: 1 + k * attempts
    assert np.all((nfev - 1) % per_attempt == 0)


def test_finished_samples_leave_the_batch_and_cond_follows_them():
    """Samples of very different speeds: the batch shrinks call by call, and each remaining
    row still gets its own conditioning (cond = the sample's rate)."""
    rate = torch.tensor([0.1, 30.0, 1.0, 10.0, 3.0], dtype=F64)
    x0 = torch.ones(5, 2, dtype=F64)
    f = Counted(lambda x, t, r: -r[:, None] * x * torch.cos(t)[:, None], per_sample=True)
    res = rk45_ps(f, x0, 0.0, 1.0, rtol=1e-8, atol=1e-8, cond=rate)
    exact = torch.exp(-rate * math.sin(1.0))[:, None].expand(5, 2)
    torch.testing.assert_close(res.x, exact, rtol=1e-6, atol=1e-9)
    assert f.rows[0] == 5 and f.rows == sorted(f.rows, reverse=True) and f.rows[-1] == 1
    assert res.sample_evals == sum(f.rows) < res.nfe * 5
    assert res.nfe == int(res.sample_nfe.max())  # the hardest sample (rate 30) sets the calls
    assert int(res.sample_nfe.argmax()) == 1


@pytest.mark.parametrize("solver", [rk45_ps, dop853_ps])
def test_per_sample_result_does_not_depend_on_batch_mates(solver):
    """The property that lets reflow split windows across processes: a sample solved inside a
    batch is bit-identical to the same sample solved alone (elementwise field), whoever its
    batch-mates are; the shared-step rk45 is not."""
    gen = torch.Generator().manual_seed(6)
    x0 = torch.randn(16, 8, generator=gen)
    x0[3:] *= 3  # harder batch-mates force smaller shared steps
    batch = solver(cubic_field, x0, 0.0, 1.0, rtol=1e-5, atol=1e-5)
    for b in (0, 5, 15):
        alone = solver(cubic_field, x0[b:b + 1], 0.0, 1.0, rtol=1e-5, atol=1e-5)
        assert torch.equal(alone.x[0], batch.x[b])
        assert alone.sample_nfe[0] == batch.sample_nfe[b]
    shuffled = torch.randperm(16, generator=gen)
    again = solver(cubic_field, x0[shuffled], 0.0, 1.0, rtol=1e-5, atol=1e-5)
    assert torch.equal(again.x, batch.x[shuffled])
    shared = rk45(cubic_field, x0, 0.0, 1.0, rtol=1e-5, atol=1e-5)
    assert not torch.equal(rk45(cubic_field, x0[:1], 0.0, 1.0, rtol=1e-5, atol=1e-5).x[0], shared.x[0])


def test_per_sample_with_a_network_field_alone_vs_in_a_batch():
    """A real network (batched matmuls): a row solved alone and inside a batch agree to float32
    rounding; bit-identity is up to the BLAS, which may round a row differently by batch size."""
    torch.manual_seed(0)
    net = torch.nn.Sequential(torch.nn.Linear(9, 64), torch.nn.Tanh(), torch.nn.Linear(64, 8))
    x0 = torch.randn(32, 8)
    cond = torch.randn(32, 8)

    def f(x, t, c):
        return net(torch.cat([x * c, t[:, None]], dim=1))

    with torch.no_grad():
        batch = rk45_ps(f, x0, 1e-3, 1.0, cond=cond)
        alone = torch.cat([rk45_ps(f, x0[b:b + 1], 1e-3, 1.0, cond=cond[b:b + 1]).x for b in range(32)])
    torch.testing.assert_close(alone, batch.x, rtol=0, atol=1e-5)


@pytest.mark.parametrize("solver", [rk45_ps, dop853_ps])
def test_per_sample_float32_lands_on_t1_and_keeps_dtype(solver):
    seen: list[torch.Tensor] = []

    def f(x, t):
        seen.append(t)
        return torch.ones_like(x)

    x0 = torch.zeros(3, 2)
    res = solver(f, x0, 1e-3, 0.7)
    assert res.x.dtype == torch.float32
    assert max(float(t.max()) for t in seen) <= 0.7
    torch.testing.assert_close(res.x, torch.full_like(x0, 0.7 - 1e-3))
    gen = torch.Generator().manual_seed(3)
    y0 = torch.randn(32, 5, dtype=F64, generator=gen)
    r64 = solver(cubic_field, y0, 0.0, 1.0, rtol=1e-5, atol=1e-5)
    r32 = solver(cubic_field, y0.float(), 0.0, 1.0, rtol=1e-5, atol=1e-5)
    assert (r32.x.double() - r64.x).abs().max() < 1e-4


@pytest.mark.parametrize("solver", [rk45_ps, dop853_ps])
def test_per_sample_errors(solver):
    assert solver(cubic_field, torch.ones(2, 3), 0.5, 0.5).nfe == 0
    with pytest.raises(RuntimeError, match="max_steps=3 exceeded for sample"):
        solver(cubic_field, torch.randn(4, 2, dtype=F64), 0.0, 10.0, rtol=1e-10, atol=1e-10, max_steps=3)

    def nan_late(x, t, sample):  # only sample 1 blows up (rows move as others finish)
        bad = (t > 0.5) & (sample == 1)
        return torch.where(bad[:, None], torch.nan, 1.0) * torch.ones_like(x)

    with pytest.raises(RuntimeError, match="underflow for sample 1 at t=0.5"):
        solver(nan_late, torch.zeros(3, 2, dtype=F64), 0.0, 1.0, cond=torch.arange(3))
    with pytest.raises(ValueError, match="cond has 3 rows"):
        solver(lambda x, t, c: x, torch.zeros(2, 2), 0.0, 1.0, cond=torch.zeros(3, 1))
    for kw in (dict(first_step=2.0), dict(rtol=0.0, atol=0.0)):
        with pytest.raises(ValueError):
            solver(cubic_field, torch.zeros(2, 2), 0.0, 1.0, **kw)


@pytest.mark.parametrize("method", METHODS)
def test_solve_passes_cond_to_every_method(method):
    rate = torch.tensor([0.5, 2.0], dtype=F64)
    kw = {} if method in ADAPTIVE else dict(steps=1000)
    res = solve(lambda x, t, r: -r[:, None] * x, torch.ones(2, 1, dtype=F64), method, cond=rate,
                rtol=1e-8, atol=1e-8, **kw)
    torch.testing.assert_close(res.x[:, 0], torch.exp(-rate), rtol=3e-3, atol=0)
    with pytest.raises(ValueError, match="cond has 1 rows"):
        solve(lambda x, t, r: x, torch.ones(2, 1), method, cond=rate[:1], **kw)


def test_sample_evals_of_whole_batch_methods():
    res = solve(cubic_field, torch.randn(7, 2), "rk4", steps=3)
    assert res.sample_evals == 12 * 7 and res.sample_nfe is None


def test_the_configs_solver_names_are_the_solvers():
    """Configs check solver names without importing torch (sefa_model.config.SOLVERS); the
    names must be exactly the methods this module implements, and FlowConfig's own."""
    import typing

    from sefa_model.config import SOLVERS, FlowConfig

    assert set(SOLVERS) == set(METHODS)
    assert set(typing.get_args(typing.get_type_hints(FlowConfig)["solver"])) == set(METHODS)

