"""sefa_data.atomic: the one place that replaces files and directories whole."""
from __future__ import annotations

import multiprocessing as mp
import os

import pytest

from sefa_data import atomic


def test_a_failed_writer_leaves_the_old_file_and_no_leftovers(tmp_path):
    target = tmp_path / "state.json"
    atomic.write_text(target, "old")
    with pytest.raises(RuntimeError):
        with atomic.writing(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("killed mid-write")
    assert target.read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["state.json"]


def _hammer(target: str, tag: str, n: int) -> None:
    for i in range(n):
        atomic.write_text(target, f"{tag}-{i}\n" * 100)


def test_two_processes_writing_one_file_never_share_a_temporary(tmp_path):
    # The bug this guards: torchrun ranks wrote `eval_log.json.tmp` at once, and one rank's
    # rename removed the other's temporary file under it (CI failure, 2026-11-24).
    target = tmp_path / "eval_log.json"
    ctx = mp.get_context("spawn")
    procs = [ctx.Process(target=_hammer, args=(str(target), tag, 200)) for tag in "ab"]
    for p in procs:
        p.start()
    for p in procs:
        p.join(60)
    assert [p.exitcode for p in procs] == [0, 0]
    lines = set(target.read_text().splitlines())
    assert len(lines) == 1 and lines.pop() in {"a-199", "b-199"}  # one whole write, not a mix
    assert [p.name for p in tmp_path.iterdir()] == ["eval_log.json"]


def test_replace_dir_swaps_a_non_empty_directory(tmp_path):
    final, new = tmp_path / "aligned.zarr", tmp_path / "build"
    final.mkdir(); (final / "v").write_text("old")
    new.mkdir(); (new / "v").write_text("new")
    atomic.replace_dir(new, final)
    assert (final / "v").read_text() == "new"
    assert [p.name for p in tmp_path.iterdir()] == ["aligned.zarr"]


def test_replace_dir_puts_the_old_directory_back_when_the_swap_fails(tmp_path, monkeypatch):
    final, new = tmp_path / "latest", tmp_path / "build"
    final.mkdir(); (final / "v").write_text("old")
    new.mkdir(); (new / "v").write_text("new")
    real, calls = os.replace, []

    def failing_second_rename(src, dst):
        calls.append((src, dst))
        if len(calls) == 2:
            raise OSError("disk full")
        real(src, dst)
    monkeypatch.setattr(atomic.os, "replace", failing_second_rename)
    with pytest.raises(OSError):
        atomic.replace_dir(new, final)
    assert (final / "v").read_text() == "old" and (new / "v").read_text() == "new"
