"""Ctrl-C through the real `sefa` command: exit 130, one true line, no traceback, wherever it
lands (a library's string exec, start-up, an ingest's commit)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def _env() -> dict:
    return {**os.environ, "PYTHONPATH": str(REPO)}


def test_an_interrupt_inside_a_string_exec_still_exits_130(tmp_path):
    """CPython marks a KeyboardInterrupt that ends a string exec as unhandled even when caught,
    and `python -m` then dies by SIGINT (-2): the flaky resume test's cause (matplotlib runs such
    strings while it is imported at a training's first checkpoint)."""
    (tmp_path / "ki_in_exec.py").write_text(textwrap.dedent("""
        import sys
        import sefa_cli.main

        def app(**kwargs):
            exec("raise KeyboardInterrupt")

        sefa_cli.main.app = app
        sys.argv = ["sefa", "info"]
        sefa_cli.main.main()
    """))
    r = subprocess.run([sys.executable, "-m", "ki_in_exec"], cwd=tmp_path, env=_env(),
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 130, (r.returncode, r.stderr)
    assert r.stderr.strip().splitlines()[-1].startswith("interrupted")
    assert "Traceback" not in r.stderr


def test_an_interrupt_handled_inside_a_command_leaves_its_exit_code_alone(tmp_path):
    """The same flag after a KeyboardInterrupt that a command handles itself: its own exit code
    (0 here), not a death by SIGINT."""
    (tmp_path / "ki_handled.py").write_text(textwrap.dedent("""
        import sys
        import sefa_cli.main

        def app(**kwargs):
            try:
                exec("raise KeyboardInterrupt")
            except KeyboardInterrupt:
                return 0

        sefa_cli.main.app = app
        sys.argv = ["sefa", "info"]
        sefa_cli.main.main()
    """))
    r = subprocess.run([sys.executable, "-m", "ki_handled"], cwd=tmp_path, env=_env(),
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, (r.returncode, r.stderr)


def test_an_eof_error_inside_a_command_is_not_taken_for_an_interrupt(tmp_path):
    """click turns an EOFError raised anywhere in a command into Abort (a Ctrl-D at a prompt,
    which sefa never shows): an emptied file that numpy read said "interrupted" and exit 130
    although nobody interrupted anything. It is an error no check foresaw: the bug line."""
    (tmp_path / "eof_in_command.py").write_text(textwrap.dedent("""
        import sys
        import typer
        import sefa_cli.main

        app = typer.Typer()

        @app.command()
        def info():
            raise EOFError("No data left in file")

        @app.command()
        def other():
            pass

        sefa_cli.main.app = app
        sys.argv = ["sefa", "info"]
        sefa_cli.main.main()
    """))
    r = subprocess.run([sys.executable, "-m", "eof_in_command"], cwd=tmp_path, env=_env(),
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 1, (r.returncode, r.stderr)
    assert r.stderr.strip().splitlines()[-1] == (
        "error: unexpected EOFError: No data left in file (a bug in sefa: rerun with "
        "SEFA_DEBUG=1 for the traceback and report it)")
    assert "interrupted" not in r.stderr and "Traceback" not in r.stderr


def test_an_interrupt_wrapped_by_class_creation_is_still_an_interrupt(tmp_path):
    """Python 3.11 wraps a KeyboardInterrupt that lands in `__set_name__` (while a library's
    import creates classes: matplotlib's, at a training's first checkpoint) in a RuntimeError:
    it is a Ctrl-C (130, the interrupt's line), not "unexpected RuntimeError ... a bug"."""
    (tmp_path / "ki_in_set_name.py").write_text(textwrap.dedent("""
        import sys
        import sefa_cli.main

        class Descriptor:
            def __set_name__(self, owner, name):
                raise KeyboardInterrupt

        def app(**kwargs):
            class Plot:
                scale = Descriptor()

        sefa_cli.main.app = app
        sys.argv = ["sefa", "info"]
        sefa_cli.main.main()
    """))
    r = subprocess.run([sys.executable, "-m", "ki_in_set_name"], cwd=tmp_path, env=_env(),
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 130, (r.returncode, r.stderr)
    assert r.stderr.strip().splitlines()[-1].startswith("interrupted")
    assert "unexpected" not in r.stderr and "Traceback" not in r.stderr


def small_store(path: Path, shared: Path, first: int, n: int) -> Path:
    """Episodes first..first+n of the real Push-T store as a DP Zarr input (state, action)."""
    import zarr

    src = zarr.open_group(str(shared / "pusht_cchi_v7_replay.zarr"), mode="r")
    ends = src["meta/episode_ends"][: first + n]
    start = int(ends[first - 1]) if first else 0
    root = zarr.open_group(str(path), mode="w", zarr_format=2)
    for key in ("state", "action"):
        root.create_array(f"data/{key}", data=src["data"][key][start: ends[-1]])
    root.create_array("meta/episode_ends", data=ends[first:] - start)
    return path


def ingest_with_sigint_at(point: str, out: Path, *inputs: Path, nth: int = 1
                          ) -> subprocess.CompletedProcess:
    """`sefa ingest` that sends itself SIGINT at a journal point (SEFA_FAULT=<point>:sigint[:N]):
    a Ctrl-C at that exact moment, never timing luck."""
    return subprocess.run([sys.executable, "-m", "sefa_cli.main", "ingest", *map(str, inputs),
                           "--fps", "10", "--out", str(out)], cwd=REPO, capture_output=True,
                          text=True, timeout=300,
                          env={**_env(), "SEFA_FAULT": f"{point}:sigint:{nth}"},
                          preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))


def episodes(store: Path) -> int:
    from sefa_data.store.zarr_store import EpisodeStore

    return len(EpisodeStore.open(store).episode_ends)


def test_ctrl_c_while_the_append_commits_says_the_episodes_are_in(shared_data, tmp_path):
    src = small_store(tmp_path / "a.zarr", shared_data, 0, 2)
    out = tmp_path / "store.zarr"
    r = ingest_with_sigint_at("commit.retired", out, src)
    assert r.returncode == 130, r.stderr
    assert r.stderr.strip().splitlines()[-1] == (
        f"interrupted after the append was committed: {out} holds the new episodes of {src}")
    assert "as they were before" not in r.stderr and "Traceback" not in r.stderr
    assert episodes(out) == 2  # true: the store holds them, checksums and all


def test_ctrl_c_before_the_commit_point_leaves_the_store_as_it_was(shared_data, tmp_path):
    src = small_store(tmp_path / "a.zarr", shared_data, 0, 2)
    out = tmp_path / "store.zarr"
    r = ingest_with_sigint_at("commit.checksums", out, src)
    assert r.returncode == 130, r.stderr
    assert r.stderr.strip().splitlines()[-1] == (
        "interrupted: stores and artifacts are as they were before this stage")
    assert not out.exists()


def test_ctrl_c_during_the_second_input_names_the_first_as_written(shared_data, tmp_path):
    a = small_store(tmp_path / "a.zarr", shared_data, 0, 2)
    b = small_store(tmp_path / "b.zarr", shared_data, 2, 3)
    c = small_store(tmp_path / "c.zarr", shared_data, 5, 1)
    out = tmp_path / "store.zarr"
    r = ingest_with_sigint_at("commit.checksums", out, a, b, c, nth=2)  # before b commits
    assert r.returncode == 130, r.stderr
    assert r.stderr.strip().splitlines()[-1] == (
        f"interrupted: {out} holds the episodes of {a}, appended before the interrupt; {b} is not "
        f"in it; not read: {c}")
    assert episodes(out) == 2


def test_ctrl_c_while_the_libraries_load_exits_130_without_a_traceback(tmp_path):
    """A Ctrl-C during `sefa`'s imports, made certain: a `typer` that raises KeyboardInterrupt
    when imported, ahead of the real one on the path. Both entry points: `python -m sefa_cli.main`
    (torchrun, the tests) and the console script's `from sefa_cli.main import main`."""
    shadow = tmp_path / "shadow"
    shadow.mkdir()
    (shadow / "typer.py").write_text("raise KeyboardInterrupt\n")
    env = {**os.environ, "PYTHONPATH": f"{shadow}{os.pathsep}{REPO}"}
    for argv in (["-m", "sefa_cli.main", "info"],
                 ["-c", "import sys; from sefa_cli.main import main; sys.exit(main())"]):
        r = subprocess.run([sys.executable, *argv], cwd=tmp_path, env=env, capture_output=True,
                           text=True, timeout=120)
        assert r.returncode == 130, (argv, r.returncode, r.stderr)
        assert r.stderr.strip() == "interrupted while starting: nothing was read or written"
