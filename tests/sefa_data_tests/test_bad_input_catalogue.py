"""Every case of the bad-input catalogue (tests/bad_inputs.py) through the real CLI: the exit
status, one `error:` line naming what is wrong, never a traceback, and the store unchanged
(issue 12, build points 1-4 and 6; the inputs are made with h5py, zarr and rosbags, one is the
shared handover file). `python benchmarks/bad_input_catalogue.py` prints the same runs as a
table for docs/bad_input_catalogue.md.
"""

from __future__ import annotations

import json
from concurrent.futures import ThreadPoolExecutor

import pytest

from bad_inputs import all_cases, can_drop_dac, make_inputs, run_case


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    inputs = make_inputs(tmp_path_factory.mktemp("bad-inputs"))
    no_dac = can_drop_dac()
    cases = [c for c in all_cases() if no_dac or "read-only" not in c.name
             and "unreadable" not in c.name]
    work = tmp_path_factory.mktemp("cases")
    # the children mostly import numpy and zarr: three at a time on two cores
    with ThreadPoolExecutor(max_workers=3) as pool:
        return list(pool.map(lambda ic: run_case(ic[1], inputs, work / f"case{ic[0]}"),
                             enumerate(cases)))


def test_every_case_ends_as_the_catalogue_says(results):
    wrong = []
    for r in results:
        c = r.case
        problems = []
        if r.exit != c.exit:
            problems.append(f"exit {r.exit}, expected {c.exit}")
        if "Traceback" in r.stderr or "Traceback" in r.stdout:
            problems.append("a traceback")
        if c.exit == 1 and not any(ln.startswith("error: ") for ln in r.stderr.splitlines()) \
                and "--skip-failed" not in c.name:
            problems.append("no `error:` line")
        if sum(ln.startswith("error: ") for ln in r.stderr.splitlines()) > 1:
            problems.append("more than one error line")
        missing = [f for f in c.fragments if f not in r.line]
        if missing:
            problems.append(f"line lacks {missing}")
        if r.store != c.store:
            problems.append(f"store {r.store}, expected {c.store}")
        if problems:
            wrong.append(f"{c.name}: {'; '.join(problems)} | {r.line} | {r.stderr[-600:]}")
    assert not wrong, "\n".join(wrong)


def test_json_error_object_on_stdout(results):
    (r,) = [r for r in results if r.case.name.startswith("--json")]
    error = json.loads(r.stdout)["error"]
    assert error["exit_code"] == 1 and error["key"] == "--fps" and "frame rate" in error["what"]
    assert r.line == f"error: {error['message']}"


def test_the_catalogue_covers_every_class(results):
    assert {r.case.klass.split()[0] for r in results} >= {"1", "2", "3", "4", "6"}
