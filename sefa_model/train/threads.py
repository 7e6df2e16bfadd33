"""How many CPU threads a training runs with when nobody chose: measured, not guessed.

torch's default is one thread per core. On a machine whose cores other work shares, those
threads wait on each other: on 2 busy cores a training ran 2.4 steps/s with torch's 2 threads
and 12.1 with one. The cost probe that times the step's batch before the first step
(sefa_model/train/loop.py:estimate_step_seconds) is run with one thread as well, and the
training keeps the faster count, said in one line. A count the user gave (--threads, sefa.yaml's
`threads`, OMP_NUM_THREADS) is kept as it is. The count changes no setting that is kept, but
torch's CPU kernels may sum in another order with another count, so two runs of the same
settings can differ in their last bits (the thread count is in the run's first line). A run
shorter than the comparison itself (a smoke test of a few steps) is not compared: it would spend
seconds choosing for a run of a fraction of one.
"""

from __future__ import annotations

import os
import time
from typing import Callable

import numpy as np
import torch

from sefa_model.distributed import load_average, threads_given

# another count is kept only when its step is faster by more than this: a timing of a few
# small batches is noisy, and torch's own default is the better guess on an idle machine
MARGIN = 0.15
# turns of the probe per thread count: a probe of a few small batches takes milliseconds for a
# low-dim policy, where one scheduling hiccup decided the choice
ROUNDS = 3


def faster_count(seconds: dict[int, float], favoured: int, margin: float = MARGIN) -> int:
    """The thread count to keep: the fastest, when it beats the `favoured` count by more than
    `margin`; else the favoured one."""
    best = min(seconds, key=lambda n: seconds[n])
    return best if seconds[best] < (1 - margin) * seconds[favoured] else favoured


def measured_threads(estimate: Callable[[], float], device: torch.device, rounds: int = ROUNDS,
                     busy: bool | None = None, steps: int | None = None
                     ) -> tuple[float, str | None]:
    """(seconds per step, a line saying the choice or None): `estimate` (the cost probe) at
    torch's threads and at one thread in turns, `rounds` times each (a load that changes in
    between hits both counts), each count's median kept, and torch left at the faster count.
    On a machine whose load already fills its cores (`busy`; None: from the load average) a
    tie goes to one thread: a probe of milliseconds shows two threads as fast as one, where a
    whole run of them waits on each other (a low-dim training ran 0.67 s a step at 2 threads
    after a probe of 0.025 s at either count). On a device other than the CPU, with one thread
    already, or a count the user gave, the probe runs once and nothing changes. With `steps`
    (the run's steps left), a run that would take less time than the turns of the comparison
    (measured by the first probe) is not compared: torch's count is kept, one thread when the
    load fills the cores."""
    started = time.perf_counter()
    first = estimate()
    turns = (2 * rounds - 1) * (time.perf_counter() - started)
    default = torch.get_num_threads()
    if device.type != "cpu" or default <= 1 or threads_given():
        return first, None
    if busy is None:
        load, cores = load_average(), os.cpu_count()
        busy = load is not None and bool(cores) and load >= cores
    if steps is not None and steps * first < turns:
        if not busy:
            return first, None
        torch.set_num_threads(1)
        return first, (f"threads: 1 (the load fills the cores; this run of about "
                       f"{steps * first:.2g} s is shorter than timing both counts would take; "
                       f"--threads N, or `threads: N` in sefa.yaml, chooses)")
    times: dict[int, list[float]] = {default: [first], 1: []}
    try:
        for n in [1] + [default, 1] * (rounds - 1):
            torch.set_num_threads(n)
            times[n].append(estimate())
    finally:
        torch.set_num_threads(default)
    seconds = {n: float(np.median(t)) for n, t in times.items()}
    pick = faster_count(seconds, 1 if busy else default)
    torch.set_num_threads(pick)
    tie = " (a tie goes to one thread: the load fills the cores)" if busy else ""
    return seconds[pick], (f"threads: {pick} (a step timed at about {seconds[1]:.3g} s with 1 "
                           f"thread and {seconds[default]:.3g} s with {default} here, the median "
                           f"of {rounds} turns each{tie}; --threads N, or `threads: N` in "
                           f"sefa.yaml, chooses)")
