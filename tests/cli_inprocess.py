"""`sefa ARGS` run inside the test's own process, through `sefa_cli.main.main` with sys.argv set: the
CLI's whole path (typer's parsing, the checks, the one `error:` line, the exit status, what is
written) without a child's ~3.5 s of imports, most of it torch.

Use a child process instead where the process itself is under test: signals, Ctrl-C, what
happens while the libraries import, the console script, torchrun, a long training (its threads
and seeds would leak into the test process). Each test file that uses this keeps at least one of
its cases in a real child, so the entry point stays covered.
"""

from __future__ import annotations

import contextlib
import importlib
import io
import os
import signal
import subprocess
import sys
import warnings
from pathlib import Path

_SIGNALS = (signal.SIGINT, signal.SIGTERM)
# Python's own warning filters when started without -W: what a child prints on its stderr
_CHILD_FILTERS = [("default", DeprecationWarning, "__main__"), ("ignore", DeprecationWarning, ""),
                  ("ignore", PendingDeprecationWarning, ""), ("ignore", ImportWarning, ""),
                  ("ignore", ResourceWarning, "")]


def _print_warning(message, category, filename, lineno, file=None, line=None) -> None:
    sys.stderr.write(warnings.formatwarning(message, category, filename, lineno, line))


def run_cli(*args, cwd: Path | str | None = None,
            threads: int | None = None) -> subprocess.CompletedProcess:
    """What `subprocess.run(["sefa", *args], capture_output=True, text=True, cwd=cwd)` returns,
    run in this process. threads: torch's thread count during the command (what a child with
    OMP_NUM_THREADS=threads gets). The working directory, sys.argv, the signal handlers and
    torch's thread count are restored afterwards, whatever the command did."""
    argv = ["sefa", *map(str, args)]
    out, err = io.StringIO(), io.StringIO()
    saved_argv, saved_cwd = sys.argv, os.getcwd()
    saved_handlers = {s: signal.getsignal(s) for s in _SIGNALS}
    # torch is imported here only when its threads are set (the command would import it anyway)
    torch = importlib.import_module("torch") if threads is not None else sys.modules.get("torch")
    saved_threads = torch.get_num_threads() if torch is not None else None
    code: int | str | None = 0
    try:
        if cwd is not None:
            os.chdir(cwd)
        sys.argv = argv
        if threads is not None:
            torch.set_num_threads(threads)
        # warnings go to the command's stderr under a child's filters (not to pytest's
        # summary), so that "one line on stderr" means here what it means in a child
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err), \
                warnings.catch_warnings():
            warnings.resetwarnings()
            for action, category, module in _CHILD_FILTERS:
                warnings.filterwarnings(action, category=category, module=module)
            warnings.showwarning = _print_warning
            from sefa_cli.main import main

            # Python's own Ctrl-C handler, as a `sefa` started from a terminal has: a suite run
            # by a shell in the background starts with SIGINT ignored, and an earlier command may
            # have left another handler (both restored below)
            signal.signal(signal.SIGINT, signal.default_int_handler)
            try:
                main()
            except SystemExit as e:
                code = e.code
                if isinstance(code, str):  # sys.exit("text"): Python prints it and exits 1
                    print(code, file=sys.stderr)
                    code = 1
    finally:
        sys.argv = saved_argv
        os.chdir(saved_cwd)
        for s, handler in saved_handlers.items():
            if handler is not None:
                signal.signal(s, handler)
        torch = sys.modules.get("torch")
        if saved_threads is not None and torch is not None:
            torch.set_num_threads(saved_threads)
    return subprocess.CompletedProcess(argv, 0 if code is None else code, out.getvalue(),
                                       err.getvalue())
