"""`sefa convert ... --to lerobot`: anything sefa ingests, as a LeRobot v3.0 dataset.

Inputs go through the ordinary ingest path into a temporary store (a sefa store given alone
is written as it is), which is then written as LeRobot (`lerobot.writer`). Each episode's task
comes from `--task` (one for all, or one per input, in order), else from what the store
recorded (a LeRobot dataset's own tasks, kept by its ingest).

The temporary store is ``.NAME.store-PID`` beside --out. It is removed with interrupts held
(`atomic.remove_temporary`), so that a Ctrl-C or SIGTERM during the removal cannot leave half of
it; what a kill -9 leaves, the next conversion to that target removes (its process is dead). An
interrupt's line says whether anything is left. Fault points (store.journal.fault_point):
``convert.ingested`` (the temporary store is complete), ``convert.published`` (the dataset is
at --out, the temporary store not yet removed), ``convert.cleanup`` (its removal begins, with
interrupts held), ``convert.cleanup.half`` (the store is removed, its folder not) and
``convert.cleanup.done`` (removed, interrupts still held); lerobot.writer and
lerobot.video_encoder have more.
"""

from __future__ import annotations

import math
import os
import signal
import threading
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterator

from sefa_data import atomic
from sefa_data.errors import SefaInputError
from sefa_data.store.journal import fault_point
from sefa_data.store.zarr_store import EpisodeStore


def is_sefa_store(path: Path) -> bool:
    import json

    for name in (".zattrs", "zarr.json"):
        f = Path(path) / name
        if f.is_file():
            try:
                doc = json.loads(f.read_text())
            except ValueError:
                return False
            return "sefa_format" in doc.get("attributes", doc)
    return False


def episode_tasks(store: EpisodeStore, tasks: list[str], inputs: list[Path]) -> list[str]:
    """One task string per episode of the store (of an episode that LeRobot recorded with
    several tasks, the first: LeRobot's writer takes one task per frame, we one per episode)."""
    sources = store.attrs["sources"]
    source_of = store.root["meta"]["episode_source"][:]
    if len(tasks) == 1:
        return tasks * store.n_episodes
    if tasks and len(tasks) != len(inputs):
        raise SefaInputError(f"{len(tasks)} --task values for {len(inputs)} inputs: give one "
                             "task for all, or one per input", key="--task")
    by_path = dict(zip(map(str, inputs), tasks))
    out = []
    for i, s in enumerate(source_of):
        source = sources[s]
        if tasks:
            out.append(by_path[source["path"]])
            continue
        recorded = (source.get("reader") or {}).get("episode_tasks")
        local = i - source["episodes"][0]
        if not recorded or not recorded[local]:
            raise SefaInputError("no task recorded for its episodes; give --task TEXT (one for "
                                 "all inputs, or one per input)", file=source["path"],
                                 where=f"episode {i}")
        out.append(recorded[local][0])
    return out


def convert_to_lerobot(inputs: list[Path], out: Path, ingest_options, tasks: list[str],
                       codec: str = "av1", robot_type: str | None = None,
                       log: Callable[[str], None] = lambda _: None,
                       progress: Callable[[int, int], None] = lambda d, t: None,
                       stall_timeout: float | None = None) -> dict:
    """Everything is checked before any input is read: --out, the codec, the tasks, every
    input's path and format. A Ctrl-C or SIGTERM is a `ConvertInterrupted` whose line says
    whether `out` was written."""
    from sefa_data.lerobot.writer import CODECS, check_new_target, write_lerobot
    from sefa_data.lerobot.video_encoder import DEFAULT_STALL_TIMEOUT

    out = Path(out)
    inputs = [Path(p) for p in inputs]
    check_new_target(out)
    if codec not in CODECS:
        raise SefaInputError(f"unknown codec {codec!r} (choose {', '.join(CODECS)})", key="--codec")
    timeout = DEFAULT_STALL_TIMEOUT if stall_timeout is None else stall_timeout
    if not (timeout > 0 and math.isfinite(timeout)):
        raise SefaInputError(f"{timeout} is not a positive number of seconds",
                             key="--encoder-timeout")
    check_tasks(tasks, inputs)
    check_inputs(inputs)
    try:
        with _sigterm_as_interrupt():
            if len(inputs) == 1 and is_sefa_store(inputs[0]):
                store = EpisodeStore.open(inputs[0])
                return write_lerobot(inputs[0], out, episode_tasks(store, tasks, inputs), codec,
                                     robot_type, progress, timeout)
            return _convert_inputs(inputs, out, ingest_options, tasks, codec, robot_type, log,
                                   progress, timeout)
    except KeyboardInterrupt as e:
        raise ConvertInterrupted(out, _published_by_us(out), _left(out)) from e


def _convert_inputs(inputs, out, ingest_options, tasks, codec, robot_type, log, progress,
                    timeout) -> dict:
    from sefa_data.ingest import ingest
    from sefa_data.lerobot.writer import write_lerobot

    out.parent.mkdir(parents=True, exist_ok=True)
    work = atomic.owned_name(out, "store")  # removed by the next run if this one is killed
    atomic.remove_temporary(work)
    try:
        work.mkdir()
        store_path = work / "store.zarr"
        report = ingest(inputs, store_path, ingest_options, log=_InputNotes(log, store_path),
                        training_notes=False)
        if not store_path.exists():
            raise SefaInputError("no input could be read (see the lines above)")
        fault_point("convert.ingested")
        store = EpisodeStore.open(store_path)
        written = [Path(r.path) for r in report.inputs if r.status == "written"]
        if len(tasks) > 1 and len(written) != len(inputs):
            tasks = [t for t, p in zip(tasks, inputs) if p in written]
        summary = write_lerobot(store_path, out, episode_tasks(store, tasks, written), codec,
                                robot_type, progress, timeout)
        fault_point("convert.published")
    finally:
        _remove_store(work)
    return {**summary, "failed": [r.message for r in report.failed],
            "left": [str(p) for p in _left(out)]}


def _remove_store(work: Path) -> None:
    """The temporary store's removal, with interrupts held from its first step to its last
    (a signal meanwhile ends the command once it is done; see the fault points above)."""
    with atomic.interrupts_held():
        fault_point("convert.cleanup")
        atomic.remove_temporary(work / "store.zarr")
        fault_point("convert.cleanup.half")
        atomic.remove_temporary(work)
        fault_point("convert.cleanup.done")


def _left(out: Path) -> list[Path]:
    """This process's temporaries still beside `out` (a removal the file system refused)."""
    from sefa_data.lerobot.writer import TEMPORARIES

    return [p for kind in TEMPORARIES if os.path.lexists(p := atomic.owned_name(out, kind))]


def check_tasks(tasks: list[str], inputs: list[Path]) -> None:
    for t in tasks:
        if not t.strip():
            raise SefaInputError("an empty task string (LeRobot's policies are conditioned on "
                                 "it): give the words of the task", key="--task")
    if len(tasks) > 1 and len(tasks) != len(inputs):
        raise SefaInputError(f"{len(tasks)} --task values for {len(inputs)} inputs: give one "
                             "task for all, or one per input", key="--task")


def check_inputs(inputs: list[Path]) -> None:
    """Every input exists and is of a format sefa reads, before the first is read: a typo in
    the last of ten inputs is found in a second, not after nine ingests."""
    from sefa_data.ingest import check_input_path, detect_format

    for path in inputs:
        check_input_path(path)
        if not os.path.lexists(path):
            raise SefaInputError("no such file or directory", file=str(path))
        detect_format(path)


class _InputNotes:
    """Ingest's lines as a conversion's: what it *read* from each input (it writes only to a
    temporary store, which no line names; its notes about training are not asked for)."""

    def __init__(self, log: Callable[[str], None], store: Path):
        self.log, self.store = log, str(store)

    def __call__(self, line: str) -> None:
        if line.startswith("written: "):
            line = "read: " + line[len("written: "):]
        self.log(line.replace(self.store, "the conversion's temporary store"))


def _published_by_us(out: Path) -> bool:
    """After an interrupt: is `out` the dataset this process wrote? (check_new_target made sure
    nothing was there when we started; the rename refuses to replace anything)."""
    return (out / "meta" / "info.json").is_file() and not atomic.owned_name(out, "tmp").exists()


class ConvertInterrupted(KeyboardInterrupt):
    """A Ctrl-C or SIGTERM during a conversion; `line` says what is on disk: the dataset, and
    whether its temporary files are gone or left for the next conversion to remove."""

    def __init__(self, out: Path, published: bool, left: list[Path] = ()):
        temporaries = left_line(out, left) if left else "the temporary files are removed"
        if published:
            line = f"interrupted after {out} was written: it is complete ({temporaries})"
        else:
            line = f"interrupted: nothing was written ({out} was not created; {temporaries})"
        super().__init__(line)
        self.line = line


def left_line(out: Path, left: list[Path]) -> str:
    """What is left beside `out`, and who removes it."""
    it = "it" if len(left) == 1 else "them"
    return (f"{', '.join(str(p) for p in left)} is left beside it: the next `sefa convert` to "
            f"{out} removes {it} (or remove {it} yourself)")


@contextmanager
def _sigterm_as_interrupt() -> Iterator[None]:
    """SIGTERM (`kill`, a job scheduler, systemd) cleans up as a Ctrl-C does, instead of ending
    the process where it stands with its temporary files."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum, frame):
        raise KeyboardInterrupt

    before = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, before)
