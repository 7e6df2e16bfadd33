"""A kept reflow block is reused only once it checks out (sefa_model/sefa/reflow.py:BlockStore):
its file reads, holds this block's windows and the noise the seed draws for them, and matches the
digest written with it. A truncated, emptied, corrupted or swapped block file is solved again,
with one line naming the file and what is wrong, and the couplings are those of a run never
interrupted.

The blocks are real: `sefa reflow` on a three-episode Push-T store (../shared/data) with a tiny
trained flow, stopped by a Ctrl-C (fault injection, SEFA_FAULT=reflow.block:sigint:3) after 3
of its 4 blocks; the damage is done to those files on disk (truncate, a flipped byte, numpy's
own writer, a copy of another block's file)."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from test_interrupts import small_store
from test_messages import TINY, sefa

REFLOW = ("reflow", "--max-windows", "32", "--samples", "2", "--block-windows", "8")


@pytest.fixture(scope="module")
def kept(shared_data, tmp_path_factory) -> tuple[Path, Path]:
    """(a workspace whose reflow was stopped after 3 of its 4 blocks, the couplings of the same
    reflow run through)."""
    from sefa_data.ingest import IngestOptions, ingest

    tmp = tmp_path_factory.mktemp("blocks")
    ws = tmp / "ws"
    ws.mkdir()
    ingest([small_store(tmp / "a.zarr", shared_data, 0, 3)], ws / "dataset.zarr",
           IngestOptions(fps=10))
    # Euler steps: the checks do not depend on the solver, and rk45 on an untrained flow takes
    # hundreds of network calls per block
    (ws / "sefa.yaml").write_text("reflow:\n  solver: euler\n")
    code, _, err = sefa(ws, "train", *TINY, "training.max_steps=10")
    assert code == 0, err
    clean = tmp / "clean"
    shutil.copytree(ws, clean, symlinks=True)
    code, _, err = sefa(ws, *REFLOW, env={"SEFA_FAULT": "reflow.block:sigint:3"})
    assert code == 130, err
    code, _, err = sefa(clean, *REFLOW)
    assert code == 0, err
    return ws, clean / "reflow" / "iter_1" / "couplings.zarr"


def blocks_of(ws: Path) -> Path:
    (partial,) = ws.glob("runs/reflow/iter_1/.*.partial")
    return partial / "couplings.blocks"


def rerun(kept, tmp_path: Path, damage) -> tuple[str, list[str]]:
    """The interrupted workspace copied, `damage(blocks folder)`, the same command again: its
    stderr, and the lines about damaged blocks. The couplings must be the clean run's."""
    import zarr

    from sefa_data.store import journal

    ws = tmp_path / "ws"
    shutil.copytree(kept[0], ws, symlinks=True)
    blocks = blocks_of(ws)
    damage(blocks)
    code, _, err = sefa(ws, *REFLOW, env={"SEFA_FAULT": "reflow.block:sigint:1000"})
    assert code == 0, err
    assert "Traceback" not in err and "a bug in sefa" not in err
    got = zarr.open_group(str(ws / "reflow/iter_1/couplings.zarr"), mode="r")
    want = zarr.open_group(str(kept[1]), mode="r")
    for key in ("noise", "action", "window"):
        np.testing.assert_array_equal(got[key][:], want[key][:])
    damaged = [ln.replace(str(blocks), "BLOCKS") for ln in err.splitlines()
               if "a damaged block of couplings" in ln]
    # every damaged block solved again, with the one never kept (the fault point counts them)
    assert journal._reached["reflow.block"] == len(damaged) + 1
    return err, damaged


@pytest.mark.parametrize("size", [0, 2000], ids=["emptied", "truncated"])
def test_a_truncated_or_emptied_block_is_solved_again_and_said(kept, tmp_path, size) -> None:
    """Once: `unexpected BadZipFile ... (a bug in sefa)`, or for an empty file "interrupted"
    and exit 130 (click takes an EOFError for a Ctrl-D)."""
    def cut(blocks: Path) -> None:
        with open(blocks / "block_000000008.npz", "r+b") as f:
            f.truncate(size)
    _, damaged = rerun(kept, tmp_path, cut)
    why = "EOFError: No data left in file" if size == 0 else "BadZipFile"
    assert len(damaged) == 1 and damaged[0].startswith(
        f"BLOCKS/block_000000008.npz: a damaged block of couplings, not "
        f"reused (not a whole .npz file ({why}"), damaged
    assert damaged[0].endswith("solving it again")


def _flip_a_byte(blocks: Path) -> None:
    path = blocks / "block_000000016.npz"
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0x10
    path.write_bytes(bytes(data))


def _rewrite_chunks(blocks: Path) -> None:
    """Well-formed, its windows and noise right, one generated chunk changed: numpy's own
    writer, the digest left as it was written."""
    path = blocks / "block_000000016.npz"
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["action"][3, 0, 0] += 0.25
    np.savez(path, **arrays)


@pytest.mark.parametrize("damage,said", [
    (_flip_a_byte, "not a whole .npz file (BadZipFile: Bad CRC-32"),
    (_rewrite_chunks, "its content does not match the digest written with it"),
], ids=["flipped-byte", "rewritten-chunks"])
def test_a_corrupted_block_is_solved_again_and_said(kept, tmp_path, damage, said) -> None:
    _, damaged = rerun(kept, tmp_path, damage)
    assert len(damaged) == 1 and "block_000000016.npz: a damaged block" in damaged[0]
    assert said in damaged[0], damaged


def test_a_block_swapped_for_another_blocks_file_is_solved_again_and_said(kept, tmp_path) -> None:
    """Once reused silently: windows 16-23 given windows 0-7's noise and chunks, the couplings
    carrying duplicated noise into align and distill."""
    def swap(blocks: Path) -> None:
        shutil.copyfile(blocks / "block_000000000.npz", blocks / "block_000000016.npz")
    _, damaged = rerun(kept, tmp_path, swap)
    assert len(damaged) == 1 and "block_000000016.npz: a damaged block" in damaged[0]
    assert "not this block's windows" in damaged[0] and "(another block's file?)" in damaged[0]
