"""A training that nobody gave a thread count measures the cost probe with torch's threads and
with one, and keeps the faster (on 2 busy cores one thread ran 5x faster; sefa printed a hint
and kept the slow default). The probe here is a stand-in whose seconds depend on the thread
count, so the choice is exact; a count the user gave is kept and the probe runs once."""

from __future__ import annotations

import pytest
import torch

import sefa_model.distributed as distributed
from sefa_model.train.threads import faster_count, measured_threads


@pytest.fixture()
def two_threads(monkeypatch):
    before = torch.get_num_threads()
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    monkeypatch.setattr(distributed, "_threads_given", False)
    torch.set_num_threads(2)
    yield
    torch.set_num_threads(before)


def test_the_faster_count_wins_only_by_more_than_the_margin():
    assert faster_count({2: 0.41, 1: 0.08}, favoured=2) == 1
    assert faster_count({2: 0.10, 1: 0.09}, favoured=2) == 2  # 10 % is within the noise
    assert faster_count({2: 0.10, 1: 0.30}, favoured=2) == 2
    assert faster_count({2: 0.0248, 1: 0.0252}, favoured=1) == 1  # a busy machine's tie
    assert faster_count({2: 0.01, 1: 0.0252}, favoured=1) == 2


def test_a_busy_machine_gets_one_thread_and_says_so(two_threads):
    calls = []

    def probe() -> float:  # 2 threads fight over busy cores: 5x slower than one
        calls.append(torch.get_num_threads())
        return {2: 0.4, 1: 0.08}[torch.get_num_threads()]

    per_step, line = measured_threads(probe, torch.device("cpu"), busy=False)
    assert calls == [2, 1, 2, 1, 2, 1] and per_step == 0.08 and torch.get_num_threads() == 1
    assert line == ("threads: 1 (a step timed at about 0.08 s with 1 thread and 0.4 s with 2 "
                    "here, the median of 3 turns each; --threads N, or `threads: N` in "
                    "sefa.yaml, chooses)")


def test_one_slow_turn_does_not_decide(two_threads):
    """A scheduling hiccup in one turn (one thread's first probe 5x slow) is outvoted by the
    median of the turns: torch's 2 threads, faster in the other turns, are kept."""
    turns = iter([0.02, 0.103, 0.02, 0.011, 0.02, 0.012])  # 2, 1, 2, 1, 2, 1 threads
    per_step, _ = measured_threads(lambda: next(turns), torch.device("cpu"), busy=False)
    assert torch.get_num_threads() == 1 and per_step == 0.012  # one thread really is faster
    torch.set_num_threads(2)
    turns = iter([0.02, 0.103, 0.02, 0.021, 0.02, 0.022])
    measured_threads(lambda: next(turns), torch.device("cpu"), busy=False)
    assert torch.get_num_threads() == 2  # one thread is no faster in the other turns


def test_an_idle_machine_keeps_torchs_threads(two_threads):
    per_step, line = measured_threads(lambda: {2: 0.05, 1: 0.09}[torch.get_num_threads()],
                                      torch.device("cpu"), busy=False)
    assert per_step == 0.05 and torch.get_num_threads() == 2 and line.startswith("threads: 2 ")


def test_a_tie_on_a_busy_machine_goes_to_one_thread(two_threads):
    """A probe of milliseconds timed a low-dim step at 0.025 s with either count; the run at
    torch's 2 threads then took 0.67 s a step. With the cores' load full, a tie is one thread;
    two threads clearly faster in the probe are still kept."""
    probe = lambda: {2: 0.0248, 1: 0.0252}[torch.get_num_threads()]  # noqa: E731
    per_step, line = measured_threads(probe, torch.device("cpu"), busy=True)
    assert torch.get_num_threads() == 1 and per_step == 0.0252
    assert "(a tie goes to one thread: the load fills the cores)" in line
    torch.set_num_threads(2)
    measured_threads(lambda: {2: 0.01, 1: 0.0252}[torch.get_num_threads()],
                     torch.device("cpu"), busy=True)
    assert torch.get_num_threads() == 2


def test_a_count_the_user_gave_is_kept_and_the_probe_runs_once(two_threads, monkeypatch):
    calls = []
    distributed.set_threads(2)  # --threads 2
    per_step, line = measured_threads(lambda: calls.append(1) or 0.4, torch.device("cpu"))
    assert (calls, per_step, line, torch.get_num_threads()) == ([1], 0.4, None, 2)
    monkeypatch.setattr(distributed, "_threads_given", False)
    monkeypatch.setenv("OMP_NUM_THREADS", "2")  # chosen through the environment
    assert measured_threads(lambda: 0.4, torch.device("cpu"))[1] is None


def test_a_run_shorter_than_the_comparison_is_not_compared(two_threads):
    """A probe that takes 50 ms of wall time for a step of 1 ms: a run of 10 steps (10 ms) is
    not worth the 5 more turns (250 ms) of the comparison; a run of 10,000 steps is."""
    import time

    calls = []

    def probe() -> float:
        calls.append(torch.get_num_threads())
        time.sleep(0.05)
        return {2: 0.004, 1: 0.001}[torch.get_num_threads()]

    per_step, line = measured_threads(probe, torch.device("cpu"), busy=False, steps=10)
    assert (calls, per_step, line, torch.get_num_threads()) == ([2], 0.004, None, 2)
    calls.clear()
    per_step, line = measured_threads(probe, torch.device("cpu"), busy=True, steps=10)
    assert (calls, per_step, torch.get_num_threads()) == ([2], 0.004, 1)
    assert line.startswith("threads: 1 (the load fills the cores; this run of about 0.04 s is "
                           "shorter than timing both counts would take;")
    torch.set_num_threads(2)
    calls.clear()
    per_step, line = measured_threads(probe, torch.device("cpu"), busy=False, steps=10_000)
    assert calls == [2, 1, 2, 1, 2, 1] and per_step == 0.001 and torch.get_num_threads() == 1
