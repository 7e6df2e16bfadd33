"""The demonstrations file a collector writes (robomimic layout), and how a collect treats a file
that is already there.

Layout written (what robomimic's SequenceDataset, with its default settings, and
`sefa_data.readers.hdf5` read):

    data.attrs: env_args (JSON: env_name, env_version, type, env_kwargs), total (samples),
                env_info (JSON, optional: what env_args cannot carry, e.g. a control_freq)
    data/demo_{i}/obs/<key>   (T, ...) observation before action t
    data/demo_{i}/next_obs/<key> (T, ...) observation after action t (obs shifted by one, then
                                       the observation the last action led to)
    data/demo_{i}/actions     (T, Da)  what the env executed
    data/demo_{i}/rewards     (T,)     env reward after action t
    data/demo_{i}/dones       (T,)     1 on the last step
    data/demo_{i}/states      (T, S)   flattened MuJoCo state before action t
    data/demo_{i}.attrs: num_samples, seed (the reset seed that produced it), model_file (Lift's
                         MJCF, what robomimic uses to replay states)

    mask/train, mask/valid    demo names (bytes): a seeded 90/10 split, at least one demo in
                              each when there are two or more (robomimic's filter keys)

A collect never loses a recorded demonstration. Into a file that exists it refuses, unless told
`append` (the new demonstrations go after the old ones, which stay byte for byte; the same
environment, seeds not already there) or `force` (replace it). Everything about the target is
checked before the first episode is recorded (`plan_target`). The file is written beside its
place and renamed into it (an append copies the old file first), so a kill or a Ctrl-C leaves
the old file or the new one, never a mix; a killed writer's temporary is removed by the next
collect. Fault points (sefa_data.store.journal.fault_point): `collect.written` (the new file is
complete beside its place, not renamed) and `collect.published` (renamed into place).
"""

from __future__ import annotations

import json
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Literal

import h5py
import numpy as np

from sefa_data import atomic
from sefa_data.errors import ConfigError, SefaInputError
from sefa_data.ranges import SEED, count
from sefa_data.store.journal import fault_point

EPISODES = count(1, 1_000_000)  # --episodes: 0 records nothing, and is no request


@dataclass
class Episode:
    seed: int
    success: bool
    obs: dict[str, list[np.ndarray]] = field(default_factory=dict)
    actions: list[np.ndarray] = field(default_factory=list)
    rewards: list[float] = field(default_factory=list)
    states: list[np.ndarray] = field(default_factory=list)
    final_obs: dict[str, np.ndarray] = field(default_factory=dict)  # after the last action
    model_file: str = ""

    def __len__(self) -> int:
        return len(self.actions)


# ----------------------------------------------------------------------------- the target

@dataclass(frozen=True)
class Target:
    """Where a collect writes and how: a new file, appended to (`--append`) or replaced
    (`--force`). `seeds`: the seeds of the demonstrations the file holds (None where a demo
    records none); `identity`: the file's inode and mtime when planned (None: no file), which
    tells after an interrupt whether the rename happened."""

    path: Path
    mode: Literal["new", "append", "replace"] = "new"
    seeds: tuple[int | None, ...] = ()
    env_args: dict | None = None  # the file's (append)
    identity: tuple[int, int] | None = None


def plan_target(path: str | Path, episodes: int, seed: int, *, append: bool = False,
                force: bool = False) -> Target:
    """Check a collect's request and its output file before any episode is recorded: one
    SefaInputError naming the option or the file otherwise."""
    EPISODES.check(episodes, "--episodes")
    SEED.check(seed, "--seed")
    if seed + episodes - 1 > SEED.hi:
        raise ConfigError(f"{seed} with {episodes} episodes reaches seed {seed + episodes - 1}, "
                          f"past the largest seed {SEED.hi} (valid: seed + episodes - 1 <= "
                          f"{SEED.hi})", key="--seed")
    if append and force:
        raise SefaInputError("--append keeps the file's demonstrations and --force replaces "
                             "them: give one of the two", key="--append")
    path = Path(path)
    atomic.remove_dead_temporaries(path, ("tmp",))  # what a killed collect left beside it
    _check_folder(path)
    if not path.exists():
        return Target(path)
    if not path.is_file():
        raise SefaInputError("exists and is not a regular file; collect writes one HDF5 file",
                             file=str(path))
    identity = (path.stat().st_ino, path.stat().st_mtime_ns)
    if force:
        return Target(path, "replace", identity=identity)
    seeds, env_args = read_demos(path)
    if not append:
        raise SefaInputError(f"already holds {_count(seeds)} ({_seeds_words(seeds)}): --append "
                             "adds the new ones after them, --force replaces the file",
                             file=str(path))
    clash = sorted(set(seeds) & set(range(seed, seed + episodes)))
    if clash:
        later = max(s for s in seeds if s is not None) + 1
        raise SefaInputError(f"already holds the demonstration(s) of seed(s) "
                             f"{', '.join(map(str, clash))}: the same seed records the same "
                             f"episode again (choose --seed {later} or later)", file=str(path),
                             key="--seed")
    return Target(path, "append", tuple(seeds), env_args, identity)


def _check_folder(path: Path) -> None:
    if path.is_dir():
        raise SefaInputError("is a directory; collect writes one HDF5 file (give a file name, "
                             "e.g. demos.hdf5)", file=str(path))
    atomic.check_can_create(path, "the file")


def read_demos(path: Path) -> tuple[list[int | None], dict | None]:
    """The seeds of the demonstrations a file holds, in order, and its env_args; a file that
    is not a demonstrations file is one SefaInputError (it is never appended to)."""
    try:
        with h5py.File(path, "r") as f:
            data = f.get("data")
            if not isinstance(data, h5py.Group):
                raise SefaInputError("exists and has no data/ group: not a demonstrations file "
                                     "(--force replaces it)", file=str(path))
            names = sorted((n for n in data if n.startswith("demo_")),
                           key=lambda n: int(n[5:]) if n[5:].isdigit() else -1)
            seeds = [int(data[n].attrs["seed"]) if "seed" in data[n].attrs else None
                     for n in names]
            env_args = json.loads(data.attrs["env_args"]) if "env_args" in data.attrs else None
    except OSError as e:
        raise SefaInputError(f"exists and is not a readable HDF5 file ({e}); --force replaces "
                             "it", file=str(path)) from None
    return seeds, env_args


def _count(seeds: list) -> str:
    return f"{len(seeds)} demonstration{'s' if len(seeds) != 1 else ''}"


def _seeds_words(seeds: Iterable[int | None]) -> str:
    known = [s for s in seeds if s is not None]
    if not known:
        return "no seeds recorded"
    return f"seed{'s' if len(known) > 1 else ''} {', '.join(map(str, known))}"


def check_env(target: Target, env_args: dict) -> None:
    """An append adds demonstrations of the environment the file already holds, or none."""
    if target.mode != "append" or target.env_args is None:
        return
    new = json.loads(json.dumps(env_args))  # as the file would hold it
    for key in ("env_name", "type", "task", "env_kwargs", "env_version"):
        if target.env_args.get(key) != new.get(key):
            raise SefaInputError(
                f"holds demonstrations of another environment (env_args.{key}: "
                f"{_short(target.env_args.get(key))} there, {_short(new.get(key))} now); "
                "collect these into another file", file=str(target.path), key="--append")


def _short(value: Any) -> str:
    text = json.dumps(value)
    return text if len(text) <= 60 else text[:57] + "..."


# ----------------------------------------------------------------------------- recording

class CollectInterrupted(KeyboardInterrupt):
    """A Ctrl-C during a collect; `line` says what became of its file."""

    def __init__(self, target: Target, recorded: int):
        published = _renamed(target)
        if published:
            line = f"interrupted after {target.path} was written: it is complete"
        elif target.mode == "new":
            line = (f"interrupted: nothing was written ({target.path} was not created; "
                    f"{recorded} episode(s) recorded are lost)")
        else:
            line = (f"interrupted: {target.path} is as it was ({recorded} episode(s) recorded "
                    "are not in it)")
        super().__init__(line)
        self.line = line


def _renamed(target: Target) -> bool:
    try:
        st = target.path.stat()
    except OSError:
        return False
    return (st.st_ino, st.st_mtime_ns) != target.identity


def record(target: Target, seeds: Iterable[int], run: Callable[[int], Episode],
           env_args: dict, env_info: dict | None = None) -> dict:
    """Run an episode per seed, write the successful ones to `target`; the summary
    {attempted, successful, success_rate, steps, failed_seeds, seconds, demos (the file's,
    after), appended_to (demos there before, appends only)}. None succeeding writes nothing
    and is a SefaInputError."""
    check_env(target, env_args)
    kept: list[Episode] = []
    failed: list[int] = []
    seeds = list(seeds)
    start = time.perf_counter()
    try:
        for s in seeds:
            episode = run(s)
            if episode.success:
                kept.append(episode)
            else:
                failed.append(episode.seed)
        seconds = time.perf_counter() - start
        if not kept:
            raise SefaInputError(f"none of the {len(seeds)} episode(s) succeeded (seeds "
                                 f"{', '.join(map(str, failed))}): nothing written",
                                 file=str(target.path))
        if target.mode == "append":
            append_demos(target.path, kept, env_info)
        else:
            write_demos(target.path, kept, env_args, env_info)
        fault_point("collect.published")
    except KeyboardInterrupt as e:
        raise CollectInterrupted(target, len(kept)) from e
    summary = {"attempted": len(seeds), "successful": len(kept),
               "success_rate": len(kept) / len(seeds), "steps": sum(len(e) for e in kept),
               "failed_seeds": failed, "seconds": seconds,
               "demos": len(target.seeds) * (target.mode == "append") + len(kept)}
    if target.mode == "append":
        summary["appended_to"] = len(target.seeds)
    return summary


# ----------------------------------------------------------------------------- writing

def write_demos(path: Path, episodes: list[Episode], env_args: dict[str, Any],
                env_info: dict[str, Any] | None = None, val_ratio: float = 0.1,
                split_seed: int = 0) -> None:
    """Write a new file next to the target and rename it, so a reader never sees a half-written
    file. The writer of every simulator's demonstrations (Lift's and Meta-World's)."""
    with atomic.writing(path) as tmp:
        with h5py.File(tmp, "w") as f:
            data = f.create_group("data")
            data.attrs["env_args"] = json.dumps(env_args)
            if env_info is not None:
                data.attrs["env_info"] = json.dumps(env_info)
            _add_demos(f, episodes, val_ratio, split_seed)
        fault_point("collect.written")


def append_demos(path: Path, episodes: list[Episode], env_info: dict[str, Any] | None = None,
                 val_ratio: float = 0.1, split_seed: int = 0) -> None:
    """The file copied beside itself, the episodes added after its demonstrations (demo_N on),
    renamed into place. The earlier demonstrations keep their train/valid split; the new ones
    are split among themselves as a new file's would be."""
    with atomic.writing(path) as tmp:
        shutil.copyfile(path, tmp)
        with h5py.File(tmp, "a") as f:
            if env_info is not None and "env_info" not in f["data"].attrs:
                f["data"].attrs["env_info"] = json.dumps(env_info)
            _add_demos(f, episodes, val_ratio, split_seed)
        fault_point("collect.written")


def _add_demos(f: h5py.File, episodes: list[Episode], val_ratio: float, split_seed: int) -> None:
    from sefa_data.store.zarr_store import split_masks

    data = f["data"]
    first = len([n for n in data if n.startswith("demo_")])
    names = [f"demo_{first + i}" for i in range(len(episodes))]
    for name, episode in zip(names, episodes):
        _write_demo(data.create_group(name), episode)
    data.attrs["total"] = int(data.attrs.get("total", 0)) + sum(len(e) for e in episodes)
    train, valid = split_masks(len(names), val_ratio, split_seed)
    for mask_name, chosen in (("train", train), ("valid", valid)):
        key = f"mask/{mask_name}"
        before = list(f[key][()]) if key in f else []
        if key in f:
            del f[key]
        f.create_dataset(key, data=np.array(
            before + [n.encode() for n, keep in zip(names, chosen) if keep], dtype="S"))


def _write_demo(group: h5py.Group, episode: Episode) -> None:
    obs = group.create_group("obs")
    next_obs = group.create_group("next_obs")
    for name, frames in episode.obs.items():
        compression = "gzip" if name.endswith("_image") else None
        stacked = np.stack(frames)
        obs.create_dataset(name, data=stacked, compression=compression)
        after = np.concatenate([stacked[1:], episode.final_obs[name][None]])
        next_obs.create_dataset(name, data=after, compression=compression)
    group.create_dataset("actions", data=np.stack(episode.actions))
    group.create_dataset("rewards", data=np.asarray(episode.rewards, dtype=np.float64))
    dones = np.zeros(len(episode), dtype=np.int64)
    dones[-1] = 1
    group.create_dataset("dones", data=dones)
    group.create_dataset("states", data=np.stack(episode.states))
    group.attrs["num_samples"] = len(episode)
    if episode.model_file:  # robosuite's MJCF (robomimic replays states with it)
        group.attrs["model_file"] = episode.model_file
    group.attrs["seed"] = episode.seed
