"""Whether the files a LeRobot dataset's episodes table points to are there, fetched and
readable, and the one line that says so (`lerobot.layout.referenced_files` lists them).

Published datasets are often incomplete where they are found: an upload of the tables alone
(meta/, without data/ and videos/), one missing some videos, or a git clone made without
Git LFS, where every parquet and mp4 file is a pointer of about 130 bytes
(``version https://git-lfs.github.com/spec/v1``, ``oid sha256:...``, ``size N``). Each is
found before any frame is decoded and said in one line that names every such file (a count
and the first few), so that one run tells what to fetch; a pointer is said to be one, with
the command that fetches the files (`git lfs pull`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from sefa_data.errors import SefaInputError, clip

# Git LFS's pointer files start with this line and are under 1024 bytes (its spec:
# https://github.com/git-lfs/git-lfs/blob/main/docs/spec.md)
LFS_POINTER = b"version https://git-lfs.github.com/spec/"
LFS_POINTER_MAX_BYTES = 1024
NAMED = 3  # files named in a line; the rest are counted


def is_lfs_pointer(path: Path) -> bool:
    """Whether `path` is a Git LFS pointer file, not the file it stands for."""
    try:
        if Path(path).stat().st_size >= LFS_POINTER_MAX_BYTES:
            return False
        with open(path, "rb") as f:
            return f.read(len(LFS_POINTER)) == LFS_POINTER
    except OSError:
        return False


def _listed(paths: list[Path], root: Path) -> str:
    """The first few paths (relative to the dataset), and how many more."""
    def rel(p: Path) -> str:
        try:
            return str(p.relative_to(root))
        except ValueError:
            return str(p)
    named = ", ".join(rel(p) for p in paths[:NAMED])
    return named + (f" and {len(paths) - NAMED} more" if len(paths) > NAMED else "")


FETCH = "run `git lfs pull` inside the clone to fetch the files themselves"


def lfs_error(paths: list[Path], root: Path) -> SefaInputError:
    if len(paths) == 1:
        return SefaInputError(f"a Git LFS pointer ({paths[0].stat().st_size} bytes), not the file "
                              f"itself: the clone has not fetched it; {FETCH}", file=str(paths[0]))
    return SefaInputError(f"{_lfs_part(paths, root)}; {FETCH}", file=str(root))


def _lfs_part(paths: list[Path], root: Path) -> str:
    if len(paths) == 1:
        return (f"1 file is a Git LFS pointer, not the file itself ({_listed(paths, root)}): "
                "the clone has not fetched it")
    return (f"{len(paths)} files are Git LFS pointers, not the files themselves "
            f"({_listed(paths, root)}): the clone has not fetched them")


def parquet_error(path: Path, e: BaseException, root: Path | None = None) -> SefaInputError:
    """A parquet file pyarrow could not read, in one line: a Git LFS pointer said as one."""
    if is_lfs_pointer(path):
        return lfs_error([path], root or path.parent)
    return SefaInputError(f"unreadable parquet ({clip(str(e))}): truncated or damaged",
                          file=str(path))


def read_parquet(path: Path, columns: list[str] | None = None):
    """A whole (small) parquet table; a damaged or truncated file is one line naming it."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    if not path.is_file():
        raise SefaInputError("missing", file=str(path))
    try:
        return pq.read_table(path, columns=columns)
    except (pa.ArrowException, OSError, ValueError) as e:
        raise parquet_error(path, e) from None


@dataclass
class FileCheck:
    """What is wrong with the files the chosen episodes and keys need, in the order listed."""

    missing: list[Path] = field(default_factory=list)
    pointers: list[Path] = field(default_factory=list)  # Git LFS pointers
    keys: dict[Path, str | None] = field(default_factory=dict)  # the video key of a video
    episode: dict[Path, int] = field(default_factory=dict)  # the first episode that needs it

    def error(self, root: Path) -> SefaInputError | None:
        """The one line for all of it: every file missing or not fetched (a count, the first
        few); one file alone is named with its key and the first episode that needs it."""
        if len(self.missing) + len(self.pointers) == 1:
            path = (self.missing or self.pointers)[0]
            if self.pointers:
                return lfs_error([path], root)
            what = "missing video file" if self.keys.get(path) else "missing"
            return SefaInputError(f"{what} (the episodes table points to it)", file=str(path),
                                  key=self.keys.get(path), where=f"episode {self.episode[path]}")
        parts = [self._missing_part(root)] if self.missing else []
        if self.pointers:
            parts.append(_lfs_part(self.pointers, root))
        if not parts:
            return None
        return SefaInputError("; ".join(parts) + (f"; {FETCH}" if self.pointers else ""),
                              file=str(root))

    def _missing_part(self, root: Path) -> str:
        videos = sum(1 for p in self.missing if self.keys.get(p))
        data = len(self.missing) - videos
        kinds = " and ".join(f"{n} {name} file{'s' if n > 1 else ''}" for n, name in
                             ((data, "data parquet"), (videos, "video")) if n)
        absent = [d for d in ("data", "videos") if not (root / d).exists()
                  and any(p.is_relative_to(root / d) for p in self.missing)]
        why = (f" (no {' and no '.join(d + '/' for d in absent)} folder: an upload of the tables "
               "alone; fetch the dataset's files too)") if absent else ""
        return (f"{len(self.missing)} file{'s' if len(self.missing) > 1 else ''} the episodes "
                f"table points to {'are' if len(self.missing) > 1 else 'is'} missing ({kinds}): "
                f"{_listed(self.missing, root)}{why}")
