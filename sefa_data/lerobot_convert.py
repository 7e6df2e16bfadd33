"""`sefa convert ... --to lerobot`: anything sefa ingests, as a LeRobot v3.0 dataset.

Inputs go through the ordinary ingest path into a temporary store (a sefa store given alone
is written as it is), which is then written as LeRobot (`lerobot_writer`). Each episode's task
comes from `--task` (one for all, or one per input, in order), else from what the store
recorded (a LeRobot dataset's own tasks, kept by its ingest).
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path
from typing import Callable

from sefa_data.errors import SefaInputError
from sefa_data.zarr_store import EpisodeStore


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
                       progress: Callable[[int, int], None] = lambda d, t: None) -> dict:
    from sefa_data.ingest import ingest
    from sefa_data.lerobot_writer import CODECS, write_lerobot

    out = Path(out)
    if out.exists():  # before any input is read
        raise SefaInputError("already exists (a conversion never writes into an existing "
                             "folder; choose another --out or remove it)", file=str(out))
    if codec not in CODECS:
        raise SefaInputError(f"unknown codec {codec!r} (choose {', '.join(CODECS)})", key="--codec")
    inputs = [Path(p) for p in inputs]
    if len(inputs) == 1 and is_sefa_store(inputs[0]):
        store = EpisodeStore.open(inputs[0])
        return write_lerobot(inputs[0], out, episode_tasks(store, tasks, inputs), codec,
                             robot_type, progress)
    out.parent.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=f".{out.name}.store-", dir=out.parent))
    try:
        store_path = work / "store.zarr"
        report = ingest(inputs, store_path, ingest_options, log=log)
        if not store_path.exists():
            raise SefaInputError("no input could be read (see the lines above)")
        store = EpisodeStore.open(store_path)
        written = [Path(r.path) for r in report.inputs if r.status == "written"]
        if len(tasks) > 1 and len(written) != len(inputs):
            tasks = [t for t, p in zip(tasks, inputs) if p in written]
        summary = write_lerobot(store_path, out, episode_tasks(store, tasks, written), codec,
                                robot_type, progress)
        return {**summary, "failed": [r.message for r in report.failed]}
    finally:
        shutil.rmtree(work, ignore_errors=True)
