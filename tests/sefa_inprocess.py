"""`sefa ARGS` run in this process through cli.main.main (no child's 3.5 s of imports): its
exit code, stdout and stderr, as a child process would give them."""

from __future__ import annotations

import contextlib
import io
import sys
from dataclasses import dataclass


@dataclass
class Result:
    returncode: int
    stdout: str
    stderr: str


def sefa(*args, ok: bool = True) -> Result:
    from cli.main import main

    out, err = io.StringIO(), io.StringIO()
    argv = sys.argv
    sys.argv = ["sefa", *map(str, args)]
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                main()
                code = 0
            except SystemExit as e:
                code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
    finally:
        sys.argv = argv
    r = Result(code, out.getvalue(), err.getvalue())
    if ok:
        assert r.returncode == 0, r.stderr[-3000:]
    return r
