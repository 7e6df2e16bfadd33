"""Batched ODE solvers for rectified-flow sampling, in plain torch.

The ODE is ``dx/dt = f(x, t)`` where ``f`` is a velocity field (a network in practice):

    f(x: Tensor (B, *shape), t: Tensor (B,)) -> Tensor (B, *shape)

or, when the field needs per-sample conditioning (an observation encoding), ``f(x, t, cond)``
with ``cond`` of shape ``(B, ...)`` handed to :func:`solve`; ``t`` is a ``(B,)`` tensor, so every
row may sit at its own time. Every call of ``f`` is one function evaluation (NFE), the cost that
matters when ``f`` is a network, so each solver counts them exactly and reports them in
:class:`SolveResult`, together with the rows evaluated (``sample_evals``), which is what a
network's cost is proportional to once the batch is large enough to fill the hardware.

The whole batch is integrated on ``x0``'s device and dtype; ``t`` is handed to ``f`` on that
device and dtype. Time bookkeeping (``t``, step sizes) is done in double precision (Python
floats, or float64 CPU tensors for per-sample control) so that the last step lands exactly on
``t1``.

Fixed-step methods: :func:`euler`, :func:`midpoint`, :func:`rk4` (1, 2, 4 NFE per step).

Adaptive, one shared step: :func:`rk45` ("rk45"), Dormand–Prince 5(4) with FSAL and scipy's
step-size control. The batch shares ONE step size: the error norm is the RMS over every element
of the batch, exactly as if ``scipy.integrate.solve_ivp(method="RK45")`` were run on the
flattened batch (which is how the reference implementation integrates). Consequences worth
knowing:

- the stiffest / fastest sample in the batch sets the step for all of them, so NFE is that
  of the hardest sample, and a sample's result depends (within tolerance) on its batch-mates;
- the step-size decision needs the error norm on the host, so each step attempt does one
  device-to-host sync (``.item()``) — negligible next to six network evaluations.

Adaptive, per sample: :func:`rk45_ps` ("rk45-ps", the same Dormand–Prince 5(4)) and
:func:`dop853_ps` ("dop853-ps", Dormand–Prince 8(5,3), scipy's DOP853). Each sample keeps its
own time and step size and is accepted or rejected on its own error norm (the RMS over that
sample's elements), exactly as if ``solve_ivp`` were run on each sample alone; a sample that
reaches ``t1`` leaves the batch, so later calls of ``f`` evaluate fewer rows. A sample's
result therefore does not depend on its batch-mates, up to the network itself: a batched matmul
may round a row differently at another batch size. Costs: one host sync per step attempt (the
per-sample error norms), and the stage arithmetic on per-row step sizes.

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
    steps: accepted steps (per-sample methods: summed over the samples).
    rejected: rejected step attempts (always 0 for fixed-step methods; per-sample methods:
        summed over the samples).
    sample_evals: rows evaluated, summed over the calls of ``f``; ``nfe * B`` (filled in when
        not given) unless samples leave the batch as they finish.
    sample_nfe: per-sample methods only, ``(B,)`` int64 on the CPU: the evaluations each sample
        needed, what ``solve_ivp`` reports as ``nfev`` for that sample alone.
    """

    x: Tensor
    nfe: int
    steps: int
    rejected: int = 0
    sample_evals: int | None = None
    sample_nfe: Tensor | None = None

    def __post_init__(self) -> None:
        if self.sample_evals is None:
            self.sample_evals = self.nfe * self.x.shape[0]




class SolverFailed(RuntimeError):
    """An adaptive solve that could not finish (too many steps, a step size underflow): the
    velocity field is stiff, non-finite or singular, which for a trained policy usually means
    its training diverged."""

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
                raise SolverFailed(
                    f"rk45: max_steps={max_steps} exceeded at t={t:.6g} of [{t0}, {t1}] "
                    f"({steps} accepted, {rejected} rejected, step {h_abs:.3g}); "
                    f"loosen rtol/atol or raise max_steps")
            if h_abs < min_step:
                raise SolverFailed(
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
# Adaptive pairs with per-sample step control: Dormand–Prince 5(4) and 8(5,3).
# --------------------------------------------------------------------------------------------

# DOP853 (Hairer, Nørsett & Wanner, "Solving ODEs I", II.10; the Fortran DOP853), the 12 stages
# used by a step and the two error estimators, as in scipy.integrate._ivp.dop853_coefficients
# (tests/sefa_model_tests/test_solvers.py checks every entry against scipy's). Dense-output stages are left out.
_C853 = (0.0, 0.526001519587677318785587544488e-01, 0.789002279381515978178381316732e-01,
         0.118350341907227396726757197510, 0.281649658092772603273242802490,
         0.333333333333333333333333333333, 0.25, 0.307692307692307692307692307692,
         0.651282051282051282051282051282, 0.6, 0.857142857142857142857142857142, 1.0)
_A853 = (
    (),
    (5.26001519587677318785587544488e-2,),
    (1.97250569845378994544595329183e-2, 5.91751709536136983633785987549e-2),
    (2.95875854768068491816892993775e-2, 0.0, 8.87627564304205475450678981324e-2),
    (2.41365134159266685502369798665e-1, 0.0, -8.84549479328286085344864962717e-1,
     9.24834003261792003115737966543e-1),
    (3.7037037037037037037037037037e-2, 0.0, 0.0, 1.70828608729473871279604482173e-1,
     1.25467687566822425016691814123e-1),
    (3.7109375e-2, 0.0, 0.0, 1.70252211019544039314978060272e-1,
     6.02165389804559606850219397283e-2, -1.7578125e-2),
    (3.70920001185047927108779319836e-2, 0.0, 0.0, 1.70383925712239993810214054705e-1,
     1.07262030446373284651809199168e-1, -1.53194377486244017527936158236e-2,
     8.27378916381402288758473766002e-3),
    (6.24110958716075717114429577812e-1, 0.0, 0.0, -3.36089262944694129406857109825,
     -8.68219346841726006818189891453e-1, 2.75920996994467083049415600797e1,
     2.01540675504778934086186788979e1, -4.34898841810699588477366255144e1),
    (4.77662536438264365890433908527e-1, 0.0, 0.0, -2.48811461997166764192642586468,
     -5.90290826836842996371446475743e-1, 2.12300514481811942347288949897e1,
     1.52792336328824235832596922938e1, -3.32882109689848629194453265587e1,
     -2.03312017085086261358222928593e-2),
    (-9.3714243008598732571704021658e-1, 0.0, 0.0, 5.18637242884406370830023853209,
     1.09143734899672957818500254654, -8.14978701074692612513997267357,
     -1.85200656599969598641566180701e1, 2.27394870993505042818970056734e1,
     2.49360555267965238987089396762, -3.0467644718982195003823669022),
    (2.27331014751653820792359768449, 0.0, 0.0, -1.05344954667372501984066689879e1,
     -2.00087205822486249909675718444, -1.79589318631187989172765950534e1,
     2.79488845294199600508499808837e1, -2.85899827713502369474065508674,
     -8.87285693353062954433549289258, 1.23605671757943030647266201528e1,
     6.43392746015763530355970484046e-1),
)
_B853 = (5.42937341165687622380535766363e-2, 0.0, 0.0, 0.0, 0.0,
         4.45031289275240888144113950566, 1.89151789931450038304281599044,
         -5.8012039600105847814672114227, 3.1116436695781989440891606237e-1,
         -1.52160949662516078556178806805e-1, 2.01365400804030348374776537501e-1,
         4.47106157277725905176885569043e-2)
# 5th- and 3rd-order error estimators over the 12 stages (f(x_new) has weight 0 in both).
_E5_853 = (0.1312004499419488073250102996e-1, 0.0, 0.0, 0.0, 0.0,
           -0.1225156446376204440720569753e+1, -0.4957589496572501915214079952,
           0.1664377182454986536961530415e+1, -0.3503288487499736816886487290,
           0.3341791187130174790297318841, 0.8192320648511571246570742613e-1,
           -0.2235530786388629525884427845e-1)
_E3_853 = tuple(b - e for b, e in zip(_B853, (0.244094488188976377952755905512, 0, 0, 0, 0, 0, 0, 0,
                                              0.733846688281611857341361741547, 0, 0,
                                              0.220588235294117647058823529412e-1)))


def _rows_rms(x: Tensor) -> Tensor:
    """RMS over each sample's elements: ``(B, *shape) -> (B,)``."""
    return x.reshape(x.shape[0], -1).pow(2).mean(dim=1).sqrt()


def _rows_sumsq(x: Tensor) -> Tensor:
    return x.reshape(x.shape[0], -1).pow(2).sum(dim=1)


def _dp54_error_norm(ks: list[Tensor], h: Tensor, scale: Tensor) -> Tensor:
    """scipy RK45's norm, per sample: ``RMS(h * sum_i E_i k_i / scale)``."""
    return _rows_rms(h * _weighted(_E, ks) / scale)


def _dop853_error_norm(ks: list[Tensor], h: Tensor, scale: Tensor) -> Tensor:
    """scipy DOP853's norm, per sample: the 5th-order estimate damped by the 3rd-order one,
    ``|h| * |e5|^2 / sqrt(n * (|e5|^2 + 0.01 |e3|^2))`` (Hairer's DOP853, 0 when both vanish)."""
    e5 = _rows_sumsq(_weighted(_E5_853, ks[:12]) / scale)
    e3 = _rows_sumsq(_weighted(_E3_853, ks[:12]) / scale)
    n = scale[0].numel()
    norm = h.reshape(-1).abs() * e5 / torch.sqrt((e5 + 0.01 * e3) * n)
    return torch.where((e5 == 0) & (e3 == 0), torch.zeros_like(norm), norm)


@dataclass(frozen=True)
class _Pair:
    """An embedded Runge–Kutta pair with FSAL: the step costs ``len(c)`` evaluations (stages
    1.. plus f(x_new), which is the next step's stage 0)."""

    name: str
    c: tuple[float, ...]
    a: tuple[tuple[float, ...], ...]
    b: tuple[float, ...]
    error_order: int  # order of the error estimate, as scipy's error_estimator_order
    error_norm: Callable[[list[Tensor], Tensor, Tensor], Tensor]


_DP54 = _Pair("rk45-ps", _C, _A, _B, 4, _dp54_error_norm)
_DOP853 = _Pair("dop853-ps", _C853, _A853, _B853, 7, _dop853_error_norm)


def _like(v: Tensor, x: Tensor) -> Tensor:
    """A float64 CPU controller tensor cast to ``x``'s dtype, then moved to its device (in that
    order: MPS has no float64)."""
    return v.to(x.dtype).to(x.device)


def _host(v: Tensor) -> Tensor:
    """A per-sample norm back on the CPU in float64, for the controller. Detached: a step size
    is the controller's decision, not a function to differentiate (as rk45's `.item()`); a
    gradient through it would also be NaN wherever an error norm is 0 (0 ** -1/5)."""
    return v.detach().cpu().double()


def _spacing(t: Tensor, direction: float, dtype: torch.dtype) -> Tensor:
    """Per-sample :func:`_next_after`: spacing of representable times next to ``t`` (float64,
    CPU) in the state's ``dtype``."""
    tt = t.to(dtype)
    return (torch.nextafter(tt, torch.full_like(tt, direction * math.inf)).double() - t).abs()


class _Field:
    """Calls ``f`` on the rows still active, counting calls and rows."""

    def __init__(self, f: Callable[..., Tensor], cond: Tensor | None):
        self.f, self.cond = f, cond
        self.calls = self.rows = 0

    def __call__(self, x: Tensor, t: Tensor) -> Tensor:
        self.calls += 1
        self.rows += x.shape[0]
        return self.f(x, t) if self.cond is None else self.f(x, t, self.cond)

    def keep(self, rows: Tensor) -> None:
        """Only ``rows`` (indices into the current active set) stay in the batch."""
        if self.cond is not None:
            self.cond = self.cond[rows]


def _initial_step_rows(field: _Field, x0: Tensor, f0: Tensor, t0: float, t1: float, rtol: float,
                       atol: float, error_order: int) -> Tensor:
    """:func:`_initial_step` per sample (scipy's ``select_initial_step`` on each sample alone).

    Costs one evaluation of ``f``. Returns ``|h|`` as a float64 CPU tensor ``(B,)``.
    """
    interval = abs(t1 - t0)
    direction = math.copysign(1.0, t1 - t0)
    scale = atol + x0.abs() * rtol
    d0 = _host(_rows_rms(x0 / scale))
    d1 = _host(_rows_rms(f0 / scale))
    h0 = torch.where((d0 < 1e-5) | (d1 < 1e-5), 1e-6, 0.01 * d0 / d1).clamp(max=interval)
    h0_x = _like(h0 * direction, x0).view(-1, *[1] * (x0.ndim - 1))
    f1 = field(x0 + h0_x * f0, _like(t0 + h0 * direction, x0))
    d2 = _host(_rows_rms((f1 - f0) / scale)) / h0
    h1 = torch.where((d1 <= 1e-15) & (d2 <= 1e-15), torch.clamp(h0 * 1e-3, min=1e-6),
                     (0.01 / torch.maximum(d1, d2)) ** (1 / (error_order + 1)))
    return torch.minimum(torch.minimum(100 * h0, h1), torch.tensor(interval, dtype=torch.float64))


def _per_sample(pair: _Pair, f: Callable[..., Tensor], x0: Tensor, t0: float, t1: float,
                rtol: float, atol: float, cond: Tensor | None, first_step: float | None,
                max_steps: int) -> SolveResult:
    """Integrate every sample with its own step size (scipy's controller, vectorised over the
    samples); samples that reach ``t1`` leave the batch."""
    _check_state(x0)
    t0, t1 = float(t0), float(t1)
    if rtol < 0 or atol < 0 or rtol + atol == 0:
        raise ValueError(f"need rtol >= 0, atol >= 0 and not both zero; got rtol={rtol}, atol={atol}")
    if cond is not None and cond.shape[0] != x0.shape[0]:
        raise ValueError(f"cond has {cond.shape[0]} rows but x0 has {x0.shape[0]}")
    n = x0.shape[0]
    if t0 == t1 or n == 0:
        return SolveResult(x=x0, nfe=0, steps=0, rejected=0, sample_evals=0,
                           sample_nfe=torch.zeros(n, dtype=torch.int64))
    direction = math.copysign(1.0, t1 - t0)
    device, dtype = x0.device, x0.dtype
    bcast = (-1,) + (1,) * (x0.ndim - 1)  # a per-sample (A,) vector against (A, *shape)
    c = torch.tensor(pair.c, dtype=torch.float64)[:, None]
    field = _Field(f, cond)

    f_x = field(x0, torch.full((n,), t0, device=device, dtype=dtype))
    if first_step is None:
        h_abs = _initial_step_rows(field, x0, f_x, t0, t1, rtol, atol, pair.error_order)
    else:
        if not 0 < first_step <= abs(t1 - t0):
            raise ValueError(f"first_step must be in (0, |t1 - t0|] = (0, {abs(t1 - t0)}], got {first_step}")
        h_abs = torch.full((n,), float(first_step), dtype=torch.float64)
    sample_nfe = torch.full((n,), field.calls, dtype=torch.int64)

    # The active set: rows of the batch not yet at t1. `rows` indexes the original batch; the
    # controller (t, h, flags, counters) lives on the CPU in float64, the states on `device`.
    rows = torch.arange(n)
    t = torch.full((n,), t0, dtype=torch.float64)
    retry = torch.zeros(n, dtype=torch.bool)  # last attempt rejected: don't grow, don't clamp
    attempts = torch.zeros(n, dtype=torch.int64)
    n_attempts = n_accepted = 0
    x = x0
    done_rows: list[Tensor] = []
    done_x: list[Tensor] = []
    while len(rows):
        min_step = 10 * _spacing(t, direction, dtype)
        h_abs = torch.where(retry, h_abs, torch.maximum(h_abs, min_step))
        _guard(pair.name, attempts, max_steps, h_abs, min_step, rows, t, t0, t1)
        t_new = t + direction * h_abs
        t_new = torch.where(direction * (t_new - t1) > 0, t1, t_new)  # land exactly on t1
        h = t_new - t
        h_abs = h.abs()

        x_new, f_new, error_norm = _attempt(pair, field, x, f_x, t, h, c, bcast, rtol, atol)
        attempts += 1
        n_attempts += len(rows)
        sample_nfe[rows] += len(pair.c)

        accepted = error_norm < 1  # NaN fails and is rejected, down to a step underflow
        h_abs = h_abs * _step_factor(error_norm, accepted, retry, pair.error_order)
        n_accepted += int(accepted.sum())
        retry = ~accepted
        t = torch.where(accepted, t_new, t)
        acc_x = accepted.to(device).view(bcast)
        x = torch.where(acc_x, x_new, x)
        f_x = torch.where(acc_x, f_new, f_x)

        finished = accepted & (direction * (t1 - t) <= 0)
        if bool(finished.any()):
            done_rows.append(rows[finished])
            done_x.append(x[finished.to(device)])
            keep = torch.nonzero(~finished).squeeze(1)
            keep_dev = keep.to(device)
            rows, t, h_abs, retry, attempts = rows[keep], t[keep], h_abs[keep], retry[keep], attempts[keep]
            x, f_x = x[keep_dev], f_x[keep_dev]
            field.keep(keep_dev)

    order = torch.cat(done_rows).argsort().to(device)
    return SolveResult(x=torch.cat(done_x)[order], nfe=field.calls, steps=n_accepted,
                       rejected=n_attempts - n_accepted, sample_evals=field.rows,
                       sample_nfe=sample_nfe)


def _guard(name: str, attempts: Tensor, max_steps: int, h_abs: Tensor, min_step: Tensor,
           rows: Tensor, t: Tensor, t0: float, t1: float) -> None:
    """Stop a sample that takes too many attempts, or whose step underflows."""
    if bool((attempts >= max_steps).any()):
        i = int(torch.nonzero(attempts >= max_steps)[0])
        raise SolverFailed(
            f"{name}: max_steps={max_steps} exceeded for sample {int(rows[i])} at "
            f"t={float(t[i]):.6g} of [{t0}, {t1}] (step {float(h_abs[i]):.3g}); "
            f"loosen rtol/atol or raise max_steps")
    if bool((h_abs < min_step).any()):
        i = int(torch.nonzero(h_abs < min_step)[0])
        raise SolverFailed(
            f"{name}: step size underflow for sample {int(rows[i])} at t={float(t[i]):.6g} "
            f"(step {float(h_abs[i]):.3g} < {float(min_step[i]):.3g}); the velocity field is "
            f"likely non-finite or singular there")


def _attempt(pair: _Pair, field, x: Tensor, f_x: Tensor, t: Tensor, h: Tensor, c: Tensor,
             bcast: tuple[int, ...], rtol: float, atol: float) -> tuple[Tensor, Tensor, Tensor]:
    """One attempt of the pair for every active sample, each with its own h:
    (x_new, f(x_new), the error norm per sample on the host)."""
    h_x = _like(h, x).view(bcast)
    times = _like(t + c * h, x)  # (stages, A): stage times, as scipy's t + c * h
    ks = [f_x]
    for s in range(1, len(pair.c)):
        ks.append(field(x + h_x * _weighted(pair.a[s], ks), times[s]))
    x_new = x + h_x * _weighted(pair.b, ks)
    f_new = field(x_new, _like(t + h, x))
    ks.append(f_new)
    scale = atol + torch.maximum(x.abs(), x_new.abs()) * rtol
    return x_new, f_new, _host(pair.error_norm(ks, h_x, scale))  # the one host sync


def _step_factor(error_norm: Tensor, accepted: Tensor, retry: Tensor, error_order: int) -> Tensor:
    """scipy's controller per sample: grow after an accepted step (not after a retry), shrink
    after a rejected one."""
    exponent = -1 / (error_order + 1)
    grow = torch.where(error_norm == 0, _MAX_FACTOR,
                       torch.clamp(_SAFETY * error_norm ** exponent, max=_MAX_FACTOR))
    grow = torch.where(retry, torch.clamp(grow, max=1.0), grow)
    shrink = _SAFETY * error_norm ** exponent
    shrink = torch.where(shrink > _MIN_FACTOR, shrink, _MIN_FACTOR)
    return torch.where(accepted, grow, shrink)


def rk45_ps(f: Callable[..., Tensor], x0: Tensor, t0: float = 0.0, t1: float = 1.0,
            rtol: float = 1e-5, atol: float = 1e-5, cond: Tensor | None = None,
            first_step: float | None = None, max_steps: int = 10_000) -> SolveResult:
    """Dormand–Prince 5(4) as :func:`rk45`, but every sample has its own step size.

    Each sample follows exactly the steps ``solve_ivp(method="RK45")`` takes on that sample
    alone, and leaves the batch at ``t1``. ``cond`` (B, ...), if given, is passed as
    ``f(x, t, cond)`` and sliced with the state. Per sample, NFE = 1 + 1 (initial step, unless
    ``first_step``) + 6 * attempts; ``nfe`` counts calls, ``sample_evals`` rows.
    ``max_steps`` bounds the attempts of each sample.
    """
    return _per_sample(_DP54, f, x0, t0, t1, rtol, atol, cond, first_step, max_steps)


def dop853_ps(f: Callable[..., Tensor], x0: Tensor, t0: float = 0.0, t1: float = 1.0,
              rtol: float = 1e-5, atol: float = 1e-5, cond: Tensor | None = None,
              first_step: float | None = None, max_steps: int = 10_000) -> SolveResult:
    """Dormand–Prince 8(5,3) (scipy's DOP853) with per-sample step sizes, as :func:`rk45_ps`.

    Order 8, 12 evaluations per attempt: fewer steps than 5(4) where the field is smooth and
    the tolerance tight. Per sample, NFE = 1 + 1 (initial step, unless ``first_step``)
    + 12 * attempts.
    """
    return _per_sample(_DOP853, f, x0, t0, t1, rtol, atol, cond, first_step, max_steps)


# --------------------------------------------------------------------------------------------
# Dispatch.
# --------------------------------------------------------------------------------------------

_FIXED: dict[str, Callable[..., SolveResult]] = {"euler": euler, "midpoint": midpoint, "rk4": rk4}
_PER_SAMPLE: dict[str, Callable[..., SolveResult]] = {"rk45-ps": rk45_ps, "dop853-ps": dop853_ps}
ADAPTIVE: tuple[str, ...] = ("rk45", *_PER_SAMPLE)
"""Methods that take rtol/atol and choose their own steps."""
METHODS: tuple[str, ...] = (*_FIXED, *ADAPTIVE)
# methods whose every call of f sees the whole batch (no sample leaves it early): f's input
# shapes stay fixed over the solve, so a CUDA graph of f recorded once replays at every call
WHOLE_BATCH: tuple[str, ...] = (*_FIXED, "rk45")


def solve(f: Callable[..., Tensor], x0: Tensor, method: str, *, t0: float = 0.0, t1: float = 1.0,
          steps: int | None = None, rtol: float = 1e-5, atol: float = 1e-5,
          cond: Tensor | None = None) -> SolveResult:
    """Integrate ``dx/dt = f(x, t)`` (or ``f(x, t, cond)`` when ``cond`` is given) from ``t0``
    to ``t1`` with ``method``.

    Fixed-step methods ("euler", "midpoint", "rk4") need ``steps >= 1`` and ignore rtol/atol;
    adaptive ones ("rk45", "rk45-ps", "dop853-ps") take rtol/atol and refuse ``steps`` (their
    step count is not the caller's to set). ``cond`` (B, ...) is per-sample conditioning: the
    per-sample methods hand ``f`` only the rows still being integrated.
    """
    if cond is not None and method not in _PER_SAMPLE:
        if cond.shape[0] != x0.shape[0]:
            raise ValueError(f"cond has {cond.shape[0]} rows but x0 has {x0.shape[0]}")
        field = f
        f = lambda x, t: field(x, t, cond)  # noqa: E731
    if method in _FIXED:
        if steps is None or steps < 1:
            raise ValueError(f"method {method!r} is fixed-step and needs steps >= 1, got steps={steps}")
        return _FIXED[method](f, x0, t0, t1, steps)
    if method in ADAPTIVE:
        if steps is not None:
            raise ValueError(f"method {method!r} is adaptive and takes rtol/atol, not steps")
        if method == "rk45":
            return rk45(f, x0, t0, t1, rtol=rtol, atol=atol)
        return _PER_SAMPLE[method](f, x0, t0, t1, rtol=rtol, atol=atol, cond=cond)
    raise ValueError(f"unknown ODE method {method!r}; valid: {', '.join(METHODS)}")
