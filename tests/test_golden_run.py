"""Every existing way of training a policy gives the same bits as before policies became
methods (tests/golden_run.py says what runs; tests/data/golden_run.json what it gave)."""

from __future__ import annotations

import json

import pytest
import torch

from golden_run import EXPECTED, environment, run


def test_every_existing_method_trains_and_samples_bit_for_bit(shared_data, tmp_path):
    expected = json.loads(EXPECTED.read_text())
    if expected["environment"] != environment():
        pytest.skip(f"the golden run was recorded with {expected['environment']}, this is "
                    f"{environment()}: float results differ across builds")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as recorded: a matmul's rounding may depend on the threads
    try:
        got = run(tmp_path, shared_data)
    finally:
        torch.set_num_threads(threads)
    for name, want in expected["policies"].items():
        assert got[name] == want, name
