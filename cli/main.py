"""The `sefa` command: the root app, its commands registered in `sefa --help`'s order, and `main`,
which turns every way a command ends into its exit code and one line. The commands live in a
module per group (cli/data.py, stages.py, workspace.py, evaluate.py, sim.py, deploy.py, bench.py,
about.py); each parses arguments, calls library functions and renders what they return."""

from __future__ import annotations

import json
import os
import sys


def _interrupted_while_starting() -> None:
    """A Ctrl-C while the libraries load (seconds, before `main` runs): no traceback, 130."""
    print("interrupted while starting: nothing was read or written", file=sys.stderr)
    if "--json" in sys.argv[1:]:
        print(json.dumps({"error": {"message": "interrupted", "kind": "interrupted",
                                    "exit_code": 130}}))
    exec("")  # see cli/exits.py:forget_caught_interrupt: libraries run string execs on import
    sys.exit(130)


try:
    from typing import Annotated

    import typer

    from sefa_cli.about import info, print_version
    from sefa_cli.bench import bench_app
    from sefa_cli.console import Interrupted
    from sefa_cli.data import convert, ingest, inspect
    from sefa_cli.deploy import export, serve
    from sefa_cli.evaluate import choose_execution, compare, eval_, results
    from sefa_cli.exits import (bug_exit, caused_by_interrupt, error_exit,
                                forget_caught_interrupt, interrupt_exit, os_error_line)
    from sefa_cli.sim import collect, demo
    from sefa_cli.stages import align, distill, presets, reflow, run, train
    from sefa_cli.workspace import config_app, status
    from sefa_data.errors import SefaInputError, clip
except KeyboardInterrupt:
    _interrupted_while_starting()

app = typer.Typer(add_completion=False, no_args_is_help=True,
                  context_settings={"help_option_names": ["-h", "--help"]},
                  help="Robot demonstrations to one-step visuomotor policies (Selective Flow Alignment).")


@app.callback()
def _root(version: Annotated[bool, typer.Option("--version", callback=print_version, is_eager=True,
                                                 help="Print the version and exit.")] = False) -> None:
    """Robot demonstrations to one-step visuomotor policies (Selective Flow Alignment)."""


# The commands are registered here, not with decorators in their modules: under
# `python -m sefa_cli.main` (torchrun, the tests) this module is `__main__`, and a module importing
# `sefa_cli.main` for its `app` would register on a second copy. The order is `sefa --help`'s.
app.add_typer(bench_app, name="bench", help="Measure latency (sefa bench latency) and data throughput (sefa bench data).")
# recordings and stores (cli/data.py), what is installed (cli/about.py)
app.command()(ingest)
app.command()(inspect)
app.command()(info)
# the workspace's stages (cli/stages.py) and its state (cli/workspace.py)
app.command(context_settings={"allow_extra_args": True, "ignore_unknown_options": False})(train)
app.command()(reflow)
app.command()(align)
app.command()(distill)
app.command()(run)
app.command()(presets)
app.command()(status)
app.add_typer(config_app, name="config")
# evaluations (cli/evaluate.py) and the simulators' demonstrations (cli/sim.py)
app.command(name="eval")(eval_)
app.command()(results)
app.command()(compare)
app.command(name="choose-execution")(choose_execution)
app.command()(collect)
app.command()(demo)
# deployment (cli/deploy.py), then LeRobot out (cli/data.py)
app.command()(export)
app.command()(serve)
app.command()(convert)


def main() -> None:
    as_json = "--json" in sys.argv[1:]
    try:
        # In this mode click returns typer.Exit's code, and 130 after catching a Ctrl-C itself.
        rc = app(standalone_mode=False)
        if rc == 130:
            raise KeyboardInterrupt
        sys.exit(rc if isinstance(rc, int) else 0)
    except SefaInputError as e:
        error_exit(e.line(), as_json, error=e)
    except (KeyboardInterrupt, typer.Abort, Interrupted) as e:
        if isinstance(e, typer.Abort) and isinstance(e.__cause__, EOFError):
            # click turns an EOFError raised anywhere in a command into Abort, as for a Ctrl-D
            # at a prompt (sefa has none): a file that ended early, not an interrupt
            bug_exit(e.__cause__, as_json)
        interrupt_exit(e, as_json)
    except OSError as e:  # EIO, a full disk, a file that vanished: the system's words, one line
        error_exit(os_error_line(e), as_json, kind="os")
    except MemoryError:
        error_exit("out of memory (an input or a setting asks for more than this machine has)",
                   as_json, kind="memory")
    except Exception as e:
        if type(e).__name__ == "SolverFailed":  # sefa_model.flow.solvers, not imported at start-up
            error_exit(f"{' '.join(str(e).split())} (the policy's velocity field is not finite "
                       "or too stiff here: did its training diverge?)", as_json, kind="solver")
        if caused_by_interrupt(e):
            interrupt_exit(e, as_json)
        if hasattr(e, "show") and hasattr(e, "exit_code"):  # click's usage errors (typer vendors click)
            e.show()
            if as_json:
                print(json.dumps({"error": {"message": e.format_message(), "kind": "usage",
                                            "exit_code": e.exit_code}}))
            sys.exit(e.exit_code)
        bug_exit(e, as_json)
    finally:  # whatever the exit: a Ctrl-C caught on the way must not turn it into -2
        forget_caught_interrupt()


if __name__ == "__main__":
    main()
