"""`sefa serve` with a fault injected into the policy it serves: the server tests' slow and
broken policies in a real `sefa serve` process, with no test hook in the product's code.

    SEFA_TEST_FAULT=hold:DIR python tests/serve_with_fault.py serve PATH ...
        each policy call appends a line to DIR/started, then waits until DIR/release exists
        (a request that runs exactly as long as the test needs, whatever the machine's speed)
    SEFA_TEST_FAULT=nan python tests/serve_with_fault.py serve PATH ...
        the policy computes, then answers NaN (as a diverging sampler or a broken export does)
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

import sefa_deploy.backends as backends  # noqa: E402

HOLD_AT_MOST_S = 120  # a test that never releases its policy still ends


class Faulty:
    def __init__(self, backend, fault: str):
        self.backend, self.fault = backend, fault
        self.name, self.device, self.metadata = backend.name, backend.device, backend.metadata

    def __call__(self, obs, noise, generator=None):  # the server passes a diffusion's generator
        kind, _, arg = self.fault.partition(":")
        if kind == "hold":
            control = Path(arg)
            with open(control / "started", "a") as f:
                f.write("call\n")
            end = time.monotonic() + HOLD_AT_MOST_S
            while not (control / "release").exists() and time.monotonic() < end:
                time.sleep(0.01)
        action, chunk = self.backend(obs, noise, generator=generator)
        if kind == "nan":
            return np.full_like(action, np.nan), np.full_like(chunk, np.nan)
        return action, chunk


def load_faulty(*args, **kwargs):
    return Faulty(real_load(*args, **kwargs), os.environ["SEFA_TEST_FAULT"])


real_load = backends.load_backend
backends.load_backend = load_faulty  # cli/deploy.py imports it when `serve` runs

if __name__ == "__main__":
    from sefa_cli.main import main

    main()
