"""Every case of the catalogue after the store (tests/artifact_bad_inputs.py, issue 23) through
the real CLI: the exit status, exactly one `error:` line holding the expected words, never a
traceback, and the workspace's artifacts compared byte for byte before and after the command.

The inputs: one tiny workspace built through the CLI from ../shared/data's Push-T (ingest,
train, reflow, align, distill; skipped without ../shared), copied per case and damaged there
(a flipped bit, a tensor rewritten with safetensors, config.json edited with its checksums
rewritten, a finished run turned into an interrupted one): artifact_bad_inputs.py's `damage`
functions say which. `python benchmarks/bad_input_catalogue.py` prints the same runs as the
second table of docs/bad_input_catalogue.md.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import pytest

from artifact_bad_inputs import all_cases, have_shared, make_workspace, problems, run_case


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    if not have_shared():
        pytest.skip("the tiny workspace is built from ../shared/data/pusht_cchi_v7_replay.zarr, "
                    "absent here (a user's clone has no ../shared)")
    template = make_workspace(tmp_path_factory.mktemp("artifact-inputs"))
    work = tmp_path_factory.mktemp("artifact-cases")
    # each child mostly imports torch and stops at its first check: three at a time on two cores
    with ThreadPoolExecutor(max_workers=3) as pool:
        return list(pool.map(lambda ic: run_case(ic[1], template, work / f"case{ic[0]}"),
                             enumerate(all_cases())))


def test_every_case_ends_as_the_catalogue_says(results):
    wrong = [f"{r.case.name}: {'; '.join(found)} | {r.line} | {r.stderr[-600:]}"
             for r in results if (found := problems(r))]
    assert not wrong, "\n".join(wrong)


def test_the_catalogue_covers_every_artifact(results):
    assert {r.case.klass for r in results} >= {
        "checkpoints", "training", ".partial", "export", "server", "workspace", "values",
        "features", "messages"}


def test_failures_never_touch_the_published_artifacts(results):
    """Whatever a failing case's expectation says: the artifacts outside .sefa/ and the
    --out folder are byte-identical (a stricter restatement that a wrong expectation cannot
    loosen)."""
    touched = [f"{r.case.name}: {r.changed}" for r in results if r.exit != 0
               and any(not k.startswith(".sefa/") and k != "evals" for k in r.changed)]
    assert not touched, "\n".join(touched)
