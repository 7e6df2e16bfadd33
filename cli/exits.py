"""How a `sefa` command ends when it does not end well: one `error:` line on stderr (and a JSON
error object with --json), or a Ctrl-C's line and exit code 130. `cli/main.py:main` calls these."""

from __future__ import annotations

import json
import os
import sys

from sefa_cli.console import Interrupted
from sefa_data.errors import SefaInputError


def error_exit(line: str, as_json: bool, code: int = 1, error: SefaInputError | None = None,
               kind: str = "input") -> None:
    """One line on stderr; with --json also a JSON error object on stdout, for scripts."""
    print(f"error: {line}", file=sys.stderr)
    if as_json:
        fields = {"file": error.file, "key": error.key, "what": error.what, "where": error.where} \
            if error is not None else {}
        print(json.dumps({"error": {"message": line, "kind": kind, "exit_code": code, **fields}},
                         indent=2))
    sys.exit(code)


def bug_exit(e: BaseException, as_json: bool) -> None:
    """An error no check foresaw: one line saying it is a bug (the traceback with SEFA_DEBUG)."""
    if os.environ.get("SEFA_DEBUG"):
        raise e
    from sefa_data.errors import clip

    text = clip(" ".join(str(e).split()), 300)
    error_exit(f"unexpected {type(e).__name__}: {text} (a bug in sefa: rerun with "
               "SEFA_DEBUG=1 for the traceback and report it)", as_json, kind="internal")


def os_error_line(e: OSError) -> str:
    where = f"{e.filename}: " if e.filename else ""
    return f"{where}{e.strerror or e} (an operating system error while reading or writing)"


def interrupted_line(e: BaseException) -> str:
    """The interrupt's own line when it has one (what an ingest appended, what a stage kept);
    else the stage runner's promise."""
    x = e.interrupt if isinstance(e, Interrupted) else e
    return getattr(x, "line", None) or \
        "interrupted: stores and artifacts are as they were before this stage"


def caused_by_interrupt(e: BaseException) -> bool:
    """An error raised *from* a KeyboardInterrupt is the interrupt: Python 3.11 turns one that
    lands while a class is created (`__set_name__`, in a library's import) into "RuntimeError:
    Error calling __set_name__", which read as a bug in sefa."""
    seen = set()
    while e is not None and id(e) not in seen:
        if isinstance(e, KeyboardInterrupt):
            return True
        seen.add(id(e))
        e = e.__cause__
    return False


def interrupt_exit(e: BaseException, as_json: bool) -> None:
    try:
        print(interrupted_line(e), file=sys.stderr, flush=True)
        if as_json:
            print(json.dumps({"error": {"message": "interrupted", "kind": "interrupted",
                                        "exit_code": 130}}), flush=True)
    except OSError:
        # `sefa ... | tee log`: Ctrl-C reached tee too and the pipe is gone (README: `tee -i`);
        # the interrupt is still the exit status, not an error while saying so
        quiet_broken_streams()
    sys.exit(130)


def quiet_broken_streams() -> None:
    """Point stdout and stderr at /dev/null, so that Python's flush at exit does not print
    "Exception ignored ... BrokenPipeError" into a pipe nobody reads."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    for stream in (sys.stdout, sys.stderr):
        try:
            os.dup2(devnull, stream.fileno())
        except (OSError, ValueError):
            pass


def forget_caught_interrupt() -> None:
    """CPython (3.8 to 3.13 at least) raises a process-wide "unhandled KeyboardInterrupt" flag
    when a KeyboardInterrupt ends the top level of any *string* exec/eval (run_eval_code_obj),
    even one that is caught further up, and under `python -m` (torchrun, the tests) Py_RunMain
    then kills the process with SIGINT (-2) instead of exiting 130. Libraries run such strings
    while they are imported (matplotlib's, imported at a training's first checkpoint, many), so a
    Ctrl-C landing there made `sefa` exit -2 now and then. Every string exec clears the flag."""
    exec("")
