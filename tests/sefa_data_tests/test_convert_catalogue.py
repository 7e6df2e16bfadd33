"""Every case of the catalogue's `sefa convert` / `config set` table (tests/convert_bad_inputs.py)
through the real CLI in child processes: the exit status, one `error:` line holding the expected
words (or the expected report line), no traceback, and what became of the files. `python
benchmarks/bad_input_catalogue.py --only convert` prints the same runs as the table of
docs/bad_input_catalogue.md."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import pytest

from convert_bad_inputs import all_cases, have_shared, make_inputs, problems, run_case


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    inputs = make_inputs(tmp_path_factory.mktemp("convert-inputs"))
    cases = [c for c in all_cases() if c.needs in inputs]
    work = tmp_path_factory.mktemp("convert-cases")
    # each child imports numpy, pyarrow and PyAV (the trainings: torch): two at a time
    with ThreadPoolExecutor(max_workers=2) as pool:
        return list(pool.map(lambda ic: run_case(ic[1], inputs, work / f"case{ic[0]}"),
                             enumerate(cases)))


def test_every_case_ends_as_the_catalogue_says(results):
    wrong = [f"{r.case.name}: {'; '.join(found)} | {r.line} | {r.stderr[-600:]}"
             for r in results if r.exit != -1 and (found := problems(r))]
    assert not wrong, "\n".join(wrong)


def test_the_workspace_cases_ran(results):
    if not have_shared():
        pytest.skip("the Push-T store's cases need ../shared/data")
    ran = {r.case.klass for r in results if r.exit != -1}
    assert ran >= {"convert", "config set"}
