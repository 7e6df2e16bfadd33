"""Paths the user names on the command line, read against the workspace (`-w`)."""

from __future__ import annotations

from pathlib import Path


def in_workspace(workspace: Path, path: Path) -> Path:
    """A relative path names something in the workspace first (`sefa eval distill -w ws` from
    any directory means ws/distill), else in the current directory; an absolute path is itself.
    When neither exists, the workspace's, so that the error names where it was looked for."""
    if path.is_absolute():
        return path
    inside = workspace / path
    if inside.exists() or inside.is_symlink() or not path.exists():
        return inside
    return path
