"""The catalogue's cases for `sefa convert` (publishing, the encoder's watchdog, interrupts,
leftovers, odd targets and arguments), `sefa config set` and a read-only workspace (issue 33).

Each case runs the real `sefa` command in a child process (signals and kill -9 need one) and
reports its exit status, its one line and what became of the files it was pointed at. Checked
by tests/sefa_data_tests/test_convert_catalogue.py; `python benchmarks/bad_input_catalogue.py --only convert`
prints the table of docs/bad_input_catalogue.md.

Inputs: a small LeRobot v2.1 dataset written with pyarrow and PyAV (tests/sefa_data_tests/test_lerobot.py's
`write_v21`); for `config set` and `status`, a workspace whose store is the real Push-T low-dim
data (../shared/data), trained for two steps for `status`.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared" / "data"
SEFA_YAML = """\
# tuned by hand: keep these notes
train:  # the base policy
- policy.head=mlp  # small and quick
- policy.mlp_hidden_dims=[8,8]
- policy.time_embed_dim=8
- training.max_steps=2
reflow:
  iters: 2   # two rounds
"""


@dataclass
class Case:
    klass: str  # convert | config set | status
    name: str
    args: list[str]  # $IN: the dataset, $OUT: the target, $WS: the workspace, $CASE: the folder
    exit: int
    fragments: tuple[str, ...]  # what the one line must hold
    outcome: str  # what must become of the files (see `outcome`)
    fault: str | None = None  # SEFA_FAULT for the child
    during: Callable[[subprocess.Popen, Path], None] | None = None  # while it runs
    then: list[str] | None = None  # a second command (the rerun after a kill)
    prepare: Callable[[Path], None] | None = None
    made: str = "pyarrow, PyAV (a LeRobot v2.1 dataset)"
    needs: str = "dataset"  # dataset | workspace | trained


@dataclass
class Result:
    case: Case
    exit: int
    line: str
    outcome: str
    stderr: str = field(repr=False, default="")


def _when(path_of: Callable[[subprocess.Popen], Path], wait: float = 0.0):
    """A `during` that waits for a file the child makes, then `wait` seconds more."""
    def wait_for(p: subprocess.Popen, case: Path) -> None:
        deadline = time.monotonic() + 120
        while not path_of(p).exists() and p.poll() is None and time.monotonic() < deadline:
            time.sleep(0.1)
        time.sleep(wait)
    return wait_for


def _signal_when_hung(sig: int):
    def during(p: subprocess.Popen, case: Path) -> None:
        _when(lambda p: case / f".out.tmp-{p.pid}", wait=2)(p, case)
        p.send_signal(sig)
    return during


def _their_folder_when_stopped(p: subprocess.Popen, case: Path) -> None:
    """The child stopped itself (SIGSTOP) with the dataset complete, before the rename: a folder
    appears at --out then (the user, another tool), and the child goes on."""
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and p.poll() is None:
        with open(f"/proc/{p.pid}/stat") as f:
            if f.read().rsplit(")", 1)[1].split()[0] == "T":
                break
        time.sleep(0.1)
    (case / "out").mkdir()
    (case / "out" / "theirs.txt").write_text("a user's file")
    p.send_signal(signal.SIGCONT)


def _existing_folder(case: Path) -> None:
    (case / "out").mkdir()
    (case / "out" / "theirs.txt").write_text("a user's file")


def _dangling(case: Path) -> None:
    (case / "out").symlink_to(case / "nowhere")


def _a_file(case: Path) -> None:
    (case / "afile").write_text("x")


def _linked_yaml(case: Path) -> None:
    real = case / "repo" / "sefa.yaml"
    real.parent.mkdir()
    shutil.move(case / "ws" / "sefa.yaml", real)
    (case / "ws" / "sefa.yaml").symlink_to(real)


CONVERT = ["convert", "$IN", "--out", "$OUT"]


def all_cases() -> list[Case]:
    c = [
        Case("convert", "--out exists (a folder holding a file)", CONVERT, 1,
             ("out: already exists",), "their folder unchanged", prepare=_existing_folder),
        Case("convert", "a folder appears at --out while the dataset is written (the child "
             "stopped before its final rename, the folder made, the child continued)", CONVERT, 1,
             ("out: appeared while the conversion ran; it was left as it is",),
             "their folder unchanged", fault="convert.written:stop",
             during=_their_folder_when_stopped),
        Case("convert", "the AV1 encoder hangs (fault point: it sleeps for ever in its frame)",
             [*CONVERT, "--encoder-timeout", "2"], 1,
             ("the av1 encoder stalled on episode 0 (6 frames): no frame encoded in 2 s",),
             "nothing left", fault="convert.encode:hang"),
        Case("convert", "Ctrl-C while the encoder hangs", CONVERT, 130,
             ("interrupted: nothing was written",), "nothing left", fault="convert.encode:hang",
             during=_signal_when_hung(signal.SIGINT)),
        Case("convert", "SIGTERM while the encoder hangs", CONVERT, 130,
             ("interrupted: nothing was written",), "nothing left", fault="convert.encode:hang",
             during=_signal_when_hung(signal.SIGTERM)),
        Case("convert", "kill -9 after the first episode is written, then the same command",
             CONVERT, 0, ("written: $OUT: LeRobot v3.0, 2 episodes",), "$OUT written",
             fault="convert.episode", then=CONVERT),
        Case("convert", "kill -9 with the dataset published, the temporary store not yet removed, "
             "then the same command", CONVERT, 1, ("out: already exists",), "$OUT written",
             fault="convert.published", then=CONVERT),
        Case("convert", "Ctrl-C just after the dataset is published", CONVERT, 130,
             ("interrupted after $OUT was written: it is complete",), "$OUT written",
             fault="convert.published:sigint"),
        Case("convert", "SIGTERM while the temporary store is removed (half of it removed, the "
             "dataset published)", CONVERT, 130,
             ("interrupted after $OUT was written: it is complete (the temporary files are "
              "removed)",), "$OUT written", fault="convert.cleanup.half:sigterm"),
        Case("convert", "--out is a dangling symlink", CONVERT, 1,
             ("out: is a dangling symlink",), "the link unchanged", prepare=_dangling),
        Case("convert", "--out inside a file", ["convert", "$IN", "--out", "$CASE/afile/out"], 1,
             ("afile/out: $CASE/afile is not a folder",), "nothing left", prepare=_a_file),
        Case("convert", "--task ''", [*CONVERT, "--task", ""], 1,
             ("--task: an empty task string",), "nothing left"),
        Case("convert", "a second input that does not exist (nothing is read first)",
             ["convert", "$IN", "$CASE/nope", "--out", "$OUT"], 1,
             ("nope: no such file or directory",), "nothing left"),
    ]
    ws = dict(made="the Push-T store (shared data), sefa.yaml with comments", needs="workspace",
              outcome="sefa.yaml unchanged")
    c += [Case("config set", f"config set {k} {v!r}", ["config", "set", k, v, "-w", "$WS"], 1,
               (says,), **ws) for k, v, says in [
        ("train_config", "nope.yaml", "nope.yaml: train_config: file not found"),
        ("device", "tpu", "device: unknown device 'tpu'"),
        ("train.training.batch_size", "100000", "training.batch_size: 100000 is more than the "
                                                "21697 training windows"),
        ("train.shape_meta.obs_keys", "[nope]", "observation key 'nope' is not in the store"),
        ("reflow.iters", "[1", "reflow.iters: '[1' is not a YAML value"),
        ("align.eps", "-1", "align.eps: -1 is too small")]]
    c += [
        Case("config set", "config set reflow.iters 3 on a sefa.yaml that is a symlink, with "
             "comments", ["config", "set", "reflow.iters", "3", "-w", "$WS"], 0,
             ("sefa.yaml: reflow.iters = 3 (was 2)",), made=ws["made"], needs="workspace",
             outcome="only the value changed, comments and link kept", prepare=_linked_yaml),
        Case("status", "sefa status in a read-only workspace (its hash cache cannot be saved)",
             ["status", "-w", "$WS"], 0, ("next: sefa reflow",), "workspace unchanged",
             made="the Push-T store, trained 2 steps; chattr +i (root) or chmod a-w",
             needs="trained"),
    ]
    return c


# ------------------------------------------------------------------ inputs


def have_shared() -> bool:
    return (SHARED / "pusht_cchi_v7_replay.zarr").is_dir()


def make_inputs(root: Path) -> dict[str, Path]:
    """The dataset; with the shared data also a workspace template and a trained one."""
    sys.path.insert(0, str(REPO / "tests"))
    from test_lerobot import write_v21

    write_v21(root / "v21", lengths=(6, 5))
    inputs = {"dataset": root / "v21"}
    if not have_shared():
        return inputs
    run_sefa(["ingest", SHARED / "pusht_cchi_v7_replay.zarr", "--fps", "10", "--key", "keypoint",
              "--key", "state", "--key", "action", "--out", root / "store.zarr"], root)
    for name in ("workspace", "trained"):
        ws = root / name
        ws.mkdir()
        (ws / "dataset.zarr").symlink_to(root / "store.zarr")
        (ws / "sefa.yaml").write_text(SEFA_YAML)
        inputs[name] = ws
    run_sefa(["train", "-w", root / "trained"], root)
    return inputs


def run_sefa(args: list, cwd: Path) -> subprocess.CompletedProcess:
    r = subprocess.run(_command(args), cwd=cwd, env=_env(None), capture_output=True, text=True,
                       timeout=600)
    assert r.returncode == 0, r.stderr
    return r


def _command(args: list) -> list[str]:
    return [sys.executable, "-m", "sefa_cli.main", *map(str, args)]


def _env(fault: str | None) -> dict[str, str]:
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    env.pop("SEFA_FAULT", None)
    if fault:
        env["SEFA_FAULT"] = fault
    return env


# ------------------------------------------------------------------ running a case


def read_only(path: Path, on: bool) -> bool:
    """Make `path` read-only (or writable again). Root ignores permissions, so as root the
    immutable attribute does it where the file system has one (chattr); False where neither
    works."""
    items = [p for p in [path, *path.rglob("*")] if not p.is_symlink()]
    if os.geteuid() != 0:
        for p in items:
            mode = p.stat().st_mode
            p.chmod(mode & ~0o222 if on else mode | 0o200)
        return True
    if shutil.which("chattr") is None:
        return False
    r = subprocess.run(["chattr", "+i" if on else "-i", *map(str, items)], capture_output=True)
    return r.returncode == 0


def _tree(path: Path) -> dict[str, bytes]:
    return {str(p.relative_to(path)): (os.readlink(p).encode() if p.is_symlink()
                                       else p.read_bytes())
            for p in sorted(path.rglob("*")) if p.is_file() or p.is_symlink()}


def run_case(case: Case, inputs: dict[str, Path], work: Path) -> Result:
    work.mkdir(parents=True)
    if case.needs != "dataset":
        shutil.copytree(inputs[case.needs], work / "ws", symlinks=True)
    if case.prepare:
        case.prepare(work)
    subs = {"$IN": str(inputs["dataset"]), "$OUT": str(work / "out"), "$WS": str(work / "ws"),
            "$CASE": str(work)}

    def expand(args: list[str]) -> list[str]:
        out = []
        for a in args:
            for k, v in subs.items():
                a = a.replace(k, v)
            out.append(a)
        return out

    before = _tree(work)
    locked = case.klass == "status" and read_only(work / "ws", True)
    try:
        # SIGINT back to its default: a suite started in the background by a shell ignores it,
        # and the child would inherit that
        p = subprocess.Popen(_command(expand(case.args)), cwd=work, env=_env(case.fault),
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                             preexec_fn=lambda: (signal.signal(signal.SIGINT, signal.SIG_DFL),
                                                 signal.signal(signal.SIGTERM, signal.SIG_DFL)))
        if case.during:
            case.during(p, work)
        out, err = p.communicate(timeout=300)
        code = p.returncode
        if case.then:  # the rerun: its status and line are the case's
            r = subprocess.run(_command(expand(case.then)), cwd=work, env=_env(None),
                               capture_output=True, text=True, timeout=300)
            out, err, code = r.stdout, r.stderr, r.returncode
    finally:
        if locked:
            read_only(work / "ws", False)
    if case.klass == "status" and not locked:
        return Result(case, -1, "not run: cannot make a folder read-only here", "-", "")
    line = _one_line(out, err, code)
    return Result(case, code, line.replace(str(work), "$CASE"), outcome(case, work, before), err)


def _one_line(out: str, err: str, code: int) -> str:
    errors = [l for l in err.splitlines() if l.startswith("error: ")]
    if errors:
        return errors[0]
    lines = [l for l in (err + out).splitlines() if l.strip() and not l.startswith("convert ")]
    return lines[-1] if lines else ""


def outcome(case: Case, work: Path, before: dict[str, bytes]) -> str:
    """What became of the files, in the words of `Case.outcome`."""
    debris = sorted(p.name for p in work.iterdir() if p.name.startswith("."))  # beside --out
    if debris:
        return f"left behind: {', '.join(debris)}"
    if case.klass == "convert":
        if case.outcome == "their folder unchanged":
            return case.outcome if _tree(work / "out") == {"theirs.txt": b"a user's file"} \
                else "their folder CHANGED"
        if case.outcome == "the link unchanged":
            return case.outcome if os.readlink(work / "out") == str(work / "nowhere") and \
                not (work / "nowhere").exists() else "the link CHANGED"
        if (work / "out" / "meta" / "info.json").is_file():
            return "$OUT written"
        return "nothing left" if not os.path.lexists(work / "out") else "$OUT half-written?"
    if case.klass == "config set":
        yaml_now = (work / "ws" / "sefa.yaml").read_text()
        if yaml_now == SEFA_YAML and not (work / "ws" / "sefa.yaml.bak").exists():
            return "sefa.yaml unchanged"
        if os.path.islink(work / "ws" / "sefa.yaml") and yaml_now == SEFA_YAML.replace(
                "iters: 2   # two rounds", "iters: 3   # two rounds"):
            return "only the value changed, comments and link kept"
        return "sefa.yaml CHANGED otherwise"
    return "workspace unchanged" if _tree(work) == before else "workspace CHANGED"


def problems(r: Result) -> list[str]:
    c = r.case
    found = []
    if r.exit != c.exit:
        found.append(f"exit {r.exit}, expected {c.exit}")
    if "Traceback" in r.stderr or "a bug in sefa" in r.stderr:
        found.append("an internal error")
    if sum(l.startswith("error: ") for l in r.stderr.splitlines()) > 1:
        found.append("more than one error line")
    missing = [f for f in c.fragments if f.replace("$OUT", "$CASE/out") not in r.line]
    if missing:
        found.append(f"line lacks {missing}")
    if r.outcome != c.outcome:
        found.append(f"{r.outcome}, expected {c.outcome}")
    return found
