"""Batched ODE solvers for rectified-flow sampling, in plain torch.

The ODE is ``dx/dt = f(x, t)`` where ``f`` is a velocity field (a network in practice):

    f(x: Tensor (B, *shape), t: Tensor (B,)) -> Tensor (B, *shape)

Every call of ``f`` is one function evaluation (NFE), the cost that matters when ``f`` is a
network, so each solver counts them exactly and reports them in :class:`SolveResult`.

The whole batch is integrated at once, on ``x0``'s device and dtype; ``t`` is handed to ``f`` as
a ``(B,)`` tensor on that device and dtype. Time bookkeeping (``t``, step sizes) is done in
Python floats (double precision) so that the last step lands exactly on ``t1``.

Fixed-step methods: :func:`euler`, :func:`midpoint`, :func:`rk4` (1, 2, 4 NFE per step).

Adaptive method: :func:`rk45`, Dormand–Prince 5(4) with FSAL and scipy's step-size control.
The batch shares ONE step size: the error norm is the RMS over every element of the batch,
exactly as if ``scipy.integrate.solve_ivp(method="RK45")`` were run on the flattened batch
(which is how the reference implementation integrates). Consequences worth knowing:

- the stiffest / fastest sample in the batch sets the step for all of them, so NFE is that
  of the hardest sample, and a sample's result depends (within tolerance) on its batch-mates;
- the step-size decision needs the error norm on the host, so each step attempt does one
  device-to-host sync (``.item()``) — negligible next to six network evaluations.

No solver wraps its work in ``torch.no_grad()``: callers decide whether gradients flow.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor

VelocityField = Callable[[Tensor, Tensor], Tensor]
"""``f(x (B, *shape), t (B,)) -> v (B, *shape)``."""


@dataclass
class SolveResult:
    """Outcome of one integration.

    x: state at ``t1``, shape ``(B, *shape)`` like ``x0``.
    nfe: number of calls of ``f``.
    steps: accepted steps.
    rejected: rejected step attempts (always 0 for fixed-step methods).
    """

    x: Tensor
    nfe: int
    steps: int
    rejected: int = 0


def _time(t: float, x: Tensor) -> Tensor:
    """Scalar time as the ``(B,)`` tensor ``f`` expects, on ``x``'s device and dtype."""
    return torch.full((x.shape[0],), t, device=x.device, dtype=x.dtype)


def _check_state(x0: Tensor) -> None:
    if x0.ndim < 1:
        raise ValueError(f"x0 must have a batch dimension, shape (B, *shape); got shape {tuple(x0.shape)}")


def _grid(t0: float, t1: float, n_steps: int) -> list[float]:
    """``n_steps + 1`` evenly spaced times, computed from the ends (no drift) and ending exactly on ``t1``."""
    if n_steps < 1:
        raise ValueError(f"n_steps must be >= 1, got {n_steps}")
    return [t0 + (t1 - t0) * i / n_steps for i in range(n_steps)] + [t1]


# --------------------------------------------------------------------------------------------
# Fixed-step methods: one step function each, one shared driver.
# --------------------------------------------------------------------------------------------

StepFn = Callable[[VelocityField, Tensor, float, float], Tensor]


def _euler_step(f: VelocityField, x: Tensor, t: float, h: float) -> Tensor:
    return x + h * f(x, _time(t, x))


def _midpoint_step(f: VelocityField, x: Tensor, t: float, h: float) -> Tensor:
    x_mid = x + (h / 2) * f(x, _time(t, x))
    return x + h * f(x_mid, _time(t + h / 2, x))


def _rk4_step(f: VelocityField, x: Tensor, t: float, h: float) -> Tensor:
    k1 = f(x, _time(t, x))
    k2 = f(x + (h / 2) * k1, _time(t + h / 2, x))
    k3 = f(x + (h / 2) * k2, _time(t + h / 2, x))
    k4 = f(x + h * k3, _time(t + h, x))
    return x + (h / 6) * (k1 + 2 * k2 + 2 * k3 + k4)


def _fixed(step: StepFn, evals_per_step: int, f: VelocityField, x0: Tensor,
           t0: float, t1: float, n_steps: int) -> SolveResult:
    _check_state(x0)
    ts = _grid(float(t0), float(t1), n_steps)
    x = x0
    for t, t_next in zip(ts[:-1], ts[1:]):
        x = step(f, x, t, t_next - t)
    return SolveResult(x=x, nfe=evals_per_step * n_steps, steps=n_steps, rejected=0)


def euler(f: VelocityField, x0: Tensor, t0: float = 0.0, t1: float = 1.0,
          n_steps: int = 1) -> SolveResult:
    """Forward Euler, order 1, 1 NFE per step. One step is exact for a constant velocity,
    which is what a perfectly straightened (reflowed / distilled) flow is sampled with."""
    return _fixed(_euler_step, 1, f, x0, t0, t1, n_steps)


def midpoint(f: VelocityField, x0: Tensor, t0: float = 0.0, t1: float = 1.0,
             n_steps: int = 1) -> SolveResult:
    """Explicit midpoint, order 2, 2 NFE per step."""
    return _fixed(_midpoint_step, 2, f, x0, t0, t1, n_steps)


def rk4(f: VelocityField, x0: Tensor, t0: float = 0.0, t1: float = 1.0,
        n_steps: int = 1) -> SolveResult:
    """Classic Runge–Kutta, order 4, 4 NFE per step."""
    return _fixed(_rk4_step, 4, f, x0, t0, t1, n_steps)


# --------------------------------------------------------------------------------------------
# Adaptive Dormand–Prince 5(4), mirroring scipy.integrate.RK45.
# --------------------------------------------------------------------------------------------

# Butcher tableau (Dormand & Prince 1980), as in scipy's RK45.
_C = (0.0, 1 / 5, 3 / 10, 4 / 5, 8 / 9, 1.0)
_A = (
    (),
    (1 / 5,),
    (3 / 40, 9 / 40),
    (44 / 45, -56 / 15, 32 / 9),
    (19372 / 6561, -25360 / 2187, 64448 / 6561, -212 / 729),
    (9017 / 3168, -355 / 33, 46732 / 5247, 49 / 176, -5103 / 18656),
)
_B = (35 / 384, 0.0, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84)
# Difference between the 5th- and the embedded 4th-order solution; the 7th entry weighs
# f(x_new), the FSAL stage, so the error estimate costs no extra evaluation.
_E = (-71 / 57600, 0.0, 71 / 16695, -71 / 1920, 17253 / 339200, -22 / 525, 1 / 40)

_SAFETY = 0.9
_MIN_FACTOR = 0.2   # never shrink by more than 5x after a rejection
_MAX_FACTOR = 10.0  # never grow by more than 10x after an acceptance
_ERROR_ORDER = 4    # order of the embedded estimate: error ~ h ** 5
_ERROR_EXPONENT = -1 / (_ERROR_ORDER + 1)


def _weighted(coeffs: tuple[float, ...], ks: list[Tensor]) -> Tensor:
    """``sum_i coeffs[i] * ks[i]``, skipping zero coefficients (saves a pass over the state)."""
    return sum(c * k for c, k in zip(coeffs, ks) if c != 0.0)


def _rms(x: Tensor) -> float:
    """RMS over every element (the whole batch): the norm that makes the step size shared."""
    return x.pow(2).mean().sqrt().item()


def _initial_step(f: VelocityField, x0: Tensor, f0: Tensor, t0: float, t1: float,
                  rtol: float, atol: float) -> float:
    """First step size, as scipy's ``select_initial_step`` (Hairer, Nørsett & Wanner, II.4).

    Costs one evaluation of ``f``. Returns ``|h|``.
    """
    interval = abs(t1 - t0)
    direction = math.copysign(1.0, t1 - t0)
    scale = atol + x0.abs() * rtol
    d0 = _rms(x0 / scale)
    d1 = _rms(f0 / scale)
    h0 = 1e-6 if d0 < 1e-5 or d1 < 1e-5 else 0.01 * d0 / d1
    h0 = min(h0, interval)
    # Probe with one Euler step to estimate the second derivative.
    f1 = f(x0 + h0 * direction * f0, _time(t0 + h0 * direction, x0))
    d2 = _rms((f1 - f0) / scale) / h0
    if d1 <= 1e-15 and d2 <= 1e-15:
        h1 = max(1e-6, h0 * 1e-3)
    else:
        h1 = (0.01 / max(d1, d2)) ** (1 / (_ERROR_ORDER + 1))
    return min(100 * h0, h1, interval)


def _dopri_step(f: VelocityField, x: Tensor, f_x: Tensor, t: float,
                h: float) -> tuple[Tensor, Tensor, Tensor]:
    """One Dormand–Prince attempt from ``(t, x)`` with ``f_x = f(x, t)`` already known.

    Costs 6 evaluations. Returns ``(x_new, f_new, err)``, all shaped like ``x``; ``f_new`` is
    ``f(x_new, t + h)``, reused as the first stage of the next step if this one is accepted.
    """
    ks = [f_x]
    for a, c in zip(_A[1:], _C[1:]):
        ks.append(f(x + h * _weighted(a, ks), _time(t + c * h, x)))
    x_new = x + h * _weighted(_B, ks)
    f_new = f(x_new, _time(t + h, x))
    ks.append(f_new)
    err = h * _weighted(_E, ks)
    return x_new, f_new, err


def _next_after(t: float, direction: float, like: Tensor) -> float:
    """Spacing of representable times next to ``t`` in ``like``'s dtype.

    scipy uses float64 spacing; using the state's dtype means a float32 solve gives up when
    ``f`` could no longer tell two consecutive times apart, rather than looping on them.
    """
    tt = torch.tensor(t, dtype=like.dtype)
    toward = torch.tensor(direction * math.inf, dtype=like.dtype)
    return abs(torch.nextafter(tt, toward).item() - t)


def rk45(f: VelocityField, x0: Tensor, t0: float = 0.0, t1: float = 1.0, rtol: float = 1e-5,
         atol: float = 1e-5, first_step: float | None = None,
         max_steps: int = 10_000) -> SolveResult:
    """Adaptive Dormand–Prince 5(4) with FSAL, step-size control as ``scipy`` RK45.

    x0: (B, *shape). Integrates from ``t0`` to ``t1`` (either direction) and lands exactly on
    ``t1``. One step size is shared by the whole batch (see the module docstring): the error of
    an attempt is ``RMS(err / (atol + rtol * max(|x|, |x_new|)))`` over all elements, accepted
    when < 1.

    NFE = 1 (f at t0) + 1 (initial step selection, only if ``first_step`` is None)
          + 6 * (steps + rejected).

    Raises RuntimeError when more than ``max_steps`` attempts (accepted + rejected) would be
    needed, or when the step falls below the time resolution (e.g. ``f`` returns inf/NaN or
    the solution blows up). ``max_steps`` counts attempts so that it bounds the work.
    """
    _check_state(x0)
    t0, t1 = float(t0), float(t1)
    if rtol < 0 or atol < 0 or rtol + atol == 0:
        raise ValueError(f"need rtol >= 0, atol >= 0 and not both zero; got rtol={rtol}, atol={atol}")
    if t0 == t1:
        return SolveResult(x=x0, nfe=0, steps=0, rejected=0)
    direction = math.copysign(1.0, t1 - t0)

    f_x = f(x0, _time(t0, x0))
    nfe = 1
    if first_step is None:
        h_abs = _initial_step(f, x0, f_x, t0, t1, rtol, atol)
        nfe += 1
    else:
        if not 0 < first_step <= abs(t1 - t0):
            raise ValueError(f"first_step must be in (0, |t1 - t0|] = (0, {abs(t1 - t0)}], got {first_step}")
        h_abs = float(first_step)

    t, x = t0, x0
    steps = rejected = 0
    while direction * (t1 - t) > 0:
        min_step = 10 * _next_after(t, direction, x)
        h_abs = max(h_abs, min_step)
        step_rejected = False
        while True:
            if steps + rejected >= max_steps:
                raise RuntimeError(
                    f"rk45: max_steps={max_steps} exceeded at t={t:.6g} of [{t0}, {t1}] "
                    f"({steps} accepted, {rejected} rejected, step {h_abs:.3g}); "
                    f"loosen rtol/atol or raise max_steps")
            if h_abs < min_step:
                raise RuntimeError(
                    f"rk45: step size underflow at t={t:.6g} (step {h_abs:.3g} < {min_step:.3g}); "
                    f"the velocity field is likely non-finite or singular there")
            t_new = t + direction * h_abs
            if direction * (t_new - t1) > 0:
                t_new = t1  # clip the last step so the solve ends exactly on t1
            h = t_new - t
            h_abs = abs(h)

            x_new, f_new, err = _dopri_step(f, x, f_x, t, h)
            nfe += 6
            scale = atol + torch.maximum(x.abs(), x_new.abs()) * rtol
            error_norm = _rms(err / scale)

            if error_norm < 1:
                factor = _MAX_FACTOR if error_norm == 0 else min(
                    _MAX_FACTOR, _SAFETY * error_norm ** _ERROR_EXPONENT)
                if step_rejected:
                    factor = min(1.0, factor)  # don't grow right after having had to shrink
                h_abs *= factor
                break
            # A NaN error norm fails `< 1` and is rejected too; it shrinks by the min factor
            # until the step underflows and the error above is raised.
            shrink = _SAFETY * error_norm ** _ERROR_EXPONENT
            h_abs *= shrink if shrink > _MIN_FACTOR else _MIN_FACTOR
            rejected += 1
            step_rejected = True

        t, x, f_x = t_new, x_new, f_new
        steps += 1
    return SolveResult(x=x, nfe=nfe, steps=steps, rejected=rejected)


# --------------------------------------------------------------------------------------------
# Dispatch.
# --------------------------------------------------------------------------------------------

_FIXED: dict[str, Callable[..., SolveResult]] = {"euler": euler, "midpoint": midpoint, "rk4": rk4}
METHODS: tuple[str, ...] = (*_FIXED, "rk45")


def solve(f: VelocityField, x0: Tensor, method: str, *, t0: float = 0.0, t1: float = 1.0,
          steps: int | None = None, rtol: float = 1e-5, atol: float = 1e-5) -> SolveResult:
    """Integrate ``dx/dt = f(x, t)`` from ``t0`` to ``t1`` with ``method``.

    Fixed-step methods ("euler", "midpoint", "rk4") need ``steps >= 1`` and ignore rtol/atol;
    "rk45" takes rtol/atol and refuses ``steps`` (its step count is not the caller's to set).
    """
    if method in _FIXED:
        if steps is None or steps < 1:
            raise ValueError(f"method {method!r} is fixed-step and needs steps >= 1, got steps={steps}")
        return _FIXED[method](f, x0, t0, t1, steps)
    if method == "rk45":
        if steps is not None:
            raise ValueError("method 'rk45' is adaptive and takes rtol/atol, not steps")
        return rk45(f, x0, t0, t1, rtol=rtol, atol=atol)
    raise ValueError(f"unknown ODE method {method!r}; valid: {', '.join(METHODS)}")
