"""The bad-input catalogue as three tables: the episode store's cases (issue 12), the cases of
the artifacts after it (issue 23: checkpoints, training, interrupted runs, export, server), and
those of `sefa convert` and `sefa config set` (issue 33), each run through the `sefa` CLI in a
child process, with its exit status, its one line and what became of the store, the
workspace's artifacts or the files it was pointed at.

    PYTHONPATH=. python benchmarks/bad_input_catalogue.py [--markdown docs/bad_input_catalogue.md]
        [--only store|artifacts|convert]

The cases and their inputs are in tests/bad_inputs.py, tests/artifact_bad_inputs.py and
tests/convert_bad_inputs.py (the tests that check them: tests/sefa_data_tests/test_bad_input_catalogue.py,
tests/cli_tests/test_artifact_catalogue.py, tests/sefa_data_tests/test_convert_catalogue.py). With --markdown each table
replaces what follows its marker in the file (`<!-- table -->`, `<!-- artifacts table -->`,
`<!-- convert table -->`), up to the next heading.
"""

from __future__ import annotations

import argparse
import re
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))
sys.path.insert(1, str(REPO / "tests" / "sefa_data_tests"))  # test_lerobot's v2.1 writer

import artifact_bad_inputs  # noqa: E402
import convert_bad_inputs  # noqa: E402
from bad_inputs import all_cases, can_drop_dac, make_inputs, run_case  # noqa: E402

STORE_MARKER = "<!-- table -->"
ARTIFACTS_MARKER = "<!-- artifacts table -->"
CONVERT_MARKER = "<!-- convert table -->"


def _cell(text: str, tmp: str) -> str:
    return text.replace(tmp, "$TMP").replace("|", "\\|")


def store_table() -> str:
    with tempfile.TemporaryDirectory(prefix="sefa-catalogue-") as tmp:
        (Path(tmp) / "inputs").mkdir()
        inputs = make_inputs(Path(tmp) / "inputs")
        cases = all_cases()
        no_dac = can_drop_dac()
        with ThreadPoolExecutor(max_workers=3) as pool:
            results = list(pool.map(
                lambda ic: run_case(ic[1], inputs, Path(tmp) / f"case{ic[0]}")
                if no_dac or not (ic[1].name.startswith("a read-only")
                                  or "unreadable" in ic[1].name) else None,
                enumerate(cases)))
    rows = ["| # | class | case | input made with | exit | the one line | store | as expected |",
            "|---|---|---|---|---|---|---|---|"]
    for n, (case, r) in enumerate(zip(cases, results), 1):
        if r is None:
            rows.append(f"| {n} | {case.klass} | {case.name} | {case.source} | - | not run: "
                        "cannot drop root's permission override here | - | - |")
            continue
        ok = (r.exit == case.exit and r.store == case.store and "Traceback" not in r.stderr
              and all(f in r.line for f in case.fragments))
        rows.append(f"| {n} | {case.klass} | {case.name} | {case.source} | {r.exit} | "
                    f"`{_cell(r.line, tmp)}` | {r.store} | {'yes' if ok else 'NO'} |")
    return "\n".join(rows)


def artifacts_table() -> str:
    a = artifact_bad_inputs
    if not a.have_shared():
        return f"(not run: {a.SHARED / 'pusht_cchi_v7_replay.zarr'} is absent)"
    cases = a.all_cases()
    with tempfile.TemporaryDirectory(prefix="sefa-artifacts-") as tmp:
        template = a.make_workspace(Path(tmp) / "inputs")
        with ThreadPoolExecutor(max_workers=3) as pool:
            results = list(pool.map(
                lambda ic: a.run_case(ic[1], template, Path(tmp) / f"case{ic[0]}"),
                enumerate(cases)))
        rows = ["| # | class | case | input made with | command | exit | the one line | "
                "artifacts | as expected |", "|---|---|---|---|---|---|---|---|---|"]
        for n, r in enumerate(results, 1):
            c = r.case
            found = a.problems(r)
            ok = f"NO: {'; '.join(found)}" if found else f"NO: {c.known}" if c.known else "yes"
            command = " ".join(["sefa", *map(str, c.args)])
            # the case's own folder is $TMP/caseN: it reads as $CASE, its workspace copy as $WS
            line = re.sub(r"\$TMP/case\d+/ws", "$WS", _cell(r.line, tmp))
            line = re.sub(r"\$TMP/case\d+/out", "$OUT", line)
            line = re.sub(r"\$TMP/case\d+", "$CASE", line)
            rows.append(f"| {n} | {c.klass} | {c.name} | {c.made} | `{_cell(command, tmp)}` | "
                        f"{r.exit} | `{line}` | {r.artifacts} | {_cell(ok, tmp)} |")
    return "\n".join(rows)


def convert_table() -> str:
    c = convert_bad_inputs
    with tempfile.TemporaryDirectory(prefix="sefa-convert-") as tmp:
        inputs = c.make_inputs(Path(tmp) / "inputs")
        cases = c.all_cases()
        with ThreadPoolExecutor(max_workers=2) as pool:
            results = list(pool.map(
                lambda ic: c.run_case(ic[1], inputs, Path(tmp) / f"case{ic[0]}")
                if ic[1].needs in inputs else None, enumerate(cases)))
        rows = ["| # | class | case | input made with | command | exit | the one line | "
                "files | as expected |", "|---|---|---|---|---|---|---|---|---|"]
        for n, (case, r) in enumerate(zip(cases, results), 1):
            command = " ".join(["sefa", *[repr(a) if a == "" or " " in a or "[" in a else a
                                          for a in case.args]])
            if case.fault:
                command = f"SEFA_FAULT={case.fault} {command}"
            if case.then:
                command += " ; then again"
            if r is None or r.exit == -1:
                why = r.line if r is not None else f"not run: {c.SHARED} is absent"
                rows.append(f"| {n} | {case.klass} | {case.name} | {case.made} | `{command}` | "
                            f"- | {why} | - | - |")
                continue
            found = c.problems(r)
            line = _cell(r.line, tmp).replace("$CASE/out", "$OUT")
            line = line.replace("$CASE/ws", "$WS")
            rows.append(f"| {n} | {case.klass} | {case.name} | {case.made} | `{_cell(command, tmp)}` "
                        f"| {r.exit} | `{line}` | {r.outcome} | "
                        f"{'NO: ' + '; '.join(found) if found else 'yes'} |")
    return "\n".join(rows)


def _put(text: str, marker: str, table: str) -> str:
    """`table` after `marker`, replacing what was there up to the next heading (or the end)."""
    if marker not in text:
        return text.rstrip("\n") + f"\n\n{marker}\n{table}\n"
    head, rest = text.split(marker, 1)
    nxt = re.search(r"^#+ ", rest, flags=re.M)
    tail = rest[nxt.start():] if nxt else ""
    return f"{head}{marker}\n{table}\n" + (f"\n{tail}" if tail else "")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--markdown", type=Path, help="also write the tables into this file")
    ap.add_argument("--only", choices=["store", "artifacts", "convert"],
                    help="run one of the three tables")
    args = ap.parse_args()
    tables = {}
    if args.only in (None, "store"):
        tables[STORE_MARKER] = store_table()
        print(tables[STORE_MARKER])
    if args.only in (None, "artifacts"):
        tables[ARTIFACTS_MARKER] = artifacts_table()
        print(tables[ARTIFACTS_MARKER])
    if args.only in (None, "convert"):
        tables[CONVERT_MARKER] = convert_table()
        print(tables[CONVERT_MARKER])
    if args.markdown:
        text = args.markdown.read_text() if args.markdown.exists() else ""
        for marker, table in tables.items():
            text = _put(text, marker, table)
        args.markdown.write_text(text)


if __name__ == "__main__":
    main()
