"""`benchmarks/bench_scale.py --out PAGE` (what `make gpu-check` runs into docs/gpu_check.md)
rewrites its own table and nothing else of the page: the findings written there by hand stay."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="module")
def bench():
    from benchmark_module import load

    return load("bench_scale")


def test_a_run_puts_its_table_after_the_title_and_the_next_run_replaces_only_it(bench, tmp_path):
    page = tmp_path / "gpu_check.md"
    page.write_text("# GPU check\n\nWhat an earlier run found.\n\n| old | table |\n")
    bench.write_table(page, "| measurement | value |\n| a | 1 |\n")
    first = page.read_text()
    assert first == ("# GPU check\n\n" + bench.TABLE_BEGIN + "\n| measurement | value |\n| a | 1 |\n"
                     + bench.TABLE_END + "\n\nWhat an earlier run found.\n\n| old | table |\n")
    bench.write_table(page, "| measurement | value |\n| b | 2 |\n")
    assert page.read_text() == first.replace("| a | 1 |", "| b | 2 |")


def test_a_missing_page_is_made_with_its_title(bench, tmp_path):
    page = tmp_path / "new.md"
    bench.write_table(page, "| t |\n")
    assert page.read_text() == f"# GPU check\n\n{bench.TABLE_BEGIN}\n| t |\n{bench.TABLE_END}\n"
