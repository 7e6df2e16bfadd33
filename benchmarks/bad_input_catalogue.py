"""The bad-input catalogue of issue 12 as a table: each case run through the `sefa` CLI in a
child process, with its exit status, its one line and what became of the store.

    PYTHONPATH=. python benchmarks/bad_input_catalogue.py [--markdown docs/bad_input_catalogue.md]

The cases and their inputs are in tests/bad_inputs.py (the test that checks them is
tests/test_bad_input_catalogue.py).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))

from bad_inputs import all_cases, can_drop_dac, make_inputs, run_case  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--markdown", type=Path, help="also write the table to this file")
    args = ap.parse_args()
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
        line = r.line.replace(tmp, "$TMP").replace("|", "\\|")
        ok = (r.exit == case.exit and r.store == case.store and "Traceback" not in r.stderr
              and all(f in r.line for f in case.fragments))
        rows.append(f"| {n} | {case.klass} | {case.name} | {case.source} | {r.exit} | "
                    f"`{line}` | {r.store} | {'yes' if ok else 'NO'} |")
    table = "\n".join(rows)
    print(table)
    if args.markdown:
        args.markdown.write_text(args.markdown.read_text().split("<!-- table -->")[0]
                                 + "<!-- table -->\n" + table + "\n"
                                 if args.markdown.exists() else table + "\n")


if __name__ == "__main__":
    main()
