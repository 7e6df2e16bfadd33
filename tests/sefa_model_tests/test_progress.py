"""The measured rate and ETA of a running task (sefa_model/progress.py) on synthetic step times:
a warm-up whose first steps are slow (allocation, caches), then a steady rate, then a change of
load. Pure functions of (seconds, units done) samples: no clock is read."""

from __future__ import annotations

import itertools

import pytest

from sefa_model.progress import (RATE_WINDOW, RateMeter, eta_seconds, measured_rate,
                                 warmup_units)


def samples(step_seconds: list[float]) -> list[tuple[float, float]]:
    """(seconds, steps done) after each step, from (0, 0): the run's start."""
    times = itertools.accumulate(step_seconds, initial=0.0)
    return [(t, float(i)) for i, t in enumerate(times)]


TOTAL = 1000
# three slow steps (1.5 s each: one-time costs), then 0.05 s a step
WARM = [1.5] * 3 + [0.05] * 297


def test_the_warm_up_is_left_out_and_the_eta_is_the_steady_rates():
    run = samples(WARM)
    assert warmup_units(TOTAL) == 10  # 1 % of the run
    rate, first, last = measured_rate(run, TOTAL)
    assert rate == pytest.approx(20.0) and first == 10 and last == 300
    assert eta_seconds(run, TOTAL) == pytest.approx(700 * 0.05)
    # what the old estimate said from steps 2-3 alone: 1.5 s a step, 30 times the truth
    naive = (TOTAL - 3) * (run[3][0] - run[1][0]) / 2
    assert naive / eta_seconds(run, TOTAL) > 25


def test_nothing_is_said_during_the_warm_up():
    run = samples(WARM)
    assert measured_rate(run[:10], TOTAL) is None  # 9 steps done: still warming up
    assert eta_seconds(run[:11], TOTAL) is None  # the warm-up ends at step 10: one sample past it
    assert eta_seconds(run[:12], TOTAL) == pytest.approx((TOTAL - 11) * 0.05)


def test_a_slow_warm_up_ends_after_ten_seconds_whatever_the_units():
    """Steps of 30 s (an image model on a CPU): the warm-up is the first step, not 1 %."""
    run = samples([40.0] + [30.0] * 20)
    assert measured_rate(run[:4], TOTAL) == pytest.approx((1 / 30, 1, 3))
    # later, over the last minute: the last three samples
    assert measured_rate(run, TOTAL) == pytest.approx((1 / 30, 19, 21))


def test_the_rate_follows_a_change_of_load_over_the_last_window():
    """Another job takes half the core: the steps take twice as long. Once the window holds only
    the slow steps, the ETA is theirs."""
    fast, slow = [0.05] * int(2 * RATE_WINDOW / 0.05), [0.1] * int(2 * RATE_WINDOW / 0.1)
    run = samples(WARM + fast + slow)
    done = run[-1][1]
    assert eta_seconds(run, TOTAL * 10) == pytest.approx((TOTAL * 10 - done) * 0.1)
    # a window as long as the whole run averages both rates instead
    assert eta_seconds(run, TOTAL * 10, window=1e9) < (TOTAL * 10 - done) * 0.1 * 0.8


def test_the_meter_agrees_with_the_pure_function_and_keeps_only_its_window():
    run = samples(WARM + [0.1] * 2000)
    meter = RateMeter(0.0, 0.0, TOTAL * 10)
    for i, (t, d) in enumerate(run[1:], start=2):
        meter.add(d, t)
        if i % 97 == 0:
            assert meter.eta() == pytest.approx(eta_seconds(run[:i], TOTAL * 10))
    assert meter.measured() == pytest.approx(measured_rate(run, TOTAL * 10))
    assert len(meter.measuring) <= RATE_WINDOW / 0.1 + 2  # not the whole run


def test_a_resumed_run_measures_from_where_it_resumed():
    run = [(t, d + 500) for t, d in samples(WARM)]
    rate, first, _ = measured_rate(run, TOTAL)
    # the warm-up is 1 % of the 500 steps left: 5 steps
    assert first == 505 and rate == pytest.approx(20.0)
