"""Read robomimic and robosuite HDF5 demonstrations as episodes.

Three layouts, all with one ``data/demo_N`` group per demonstration:

* ``robomimic``: ``obs/<key>``, ``actions``, ``rewards``, ``dones``, ``mask/<filter>`` and a
  JSON ``env_args`` attribute. Dataset keys: ``action``, ``observation.<key>``, ``reward``,
  ``done``.
* ``robosuite`` (a raw recording, no ``obs/``): ``states`` and ``actions`` become ``state`` and
  ``action``. Every other per-demo stream is read too (``controller_info/robot_controls/action``
  becomes ``controller_info.robot_controls.action``) when it has one row per action in every
  demo; the rest (the handover file's controller and user logs run at their own rate) is skipped
  and listed in the metadata.
* ``key_map``: any other layout, by explicit dataset key to HDF5 path (relative to the demo).

The set of keys is decided once, from the shapes of every selected demo, so that all episodes
carry the same keys, dtypes and frame shapes. Structure problems of the whole file raise from
`read_hdf5`; problems of one demo (no action, an empty demo, a requested key of the wrong length,
a NaN) raise from the episode iterator when that demo is reached.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator

import h5py
import numpy as np

from sefa_data.config_io import from_dict
from sefa_data.episode import Episode, Recording
from sefa_data.errors import ConfigError, SefaInputError
from sefa_data.stats import first_nonfinite

_DEMO_NAME = re.compile(r"demo_(\d+)")
_NUMERIC_KINDS = "biufc"
# data attributes that become their own meta entries (JSON ones parsed); the rest go to
# meta["attrs"] as they are
_ENV_ATTRS = ("env_args", "env", "env_info")
_JSON_ATTRS = ("env_args", "env_info")


@dataclass
class Hdf5Options:
    obs_keys: list[str] | None = None  # None: every dataset under obs/
    action_key: str = "actions"
    # dataset key -> HDF5 path relative to the demo group; when given, only these keys are read,
    # plus `action` from action_key when the map has no "action" entry
    key_map: dict[str, str] = field(default_factory=dict)
    filter_key: str | None = None  # only the demos listed in mask/<filter_key>
    include_rewards: bool = True

    def validate(self) -> None:
        if self.key_map and self.obs_keys is not None:
            raise ConfigError("give either obs_keys or key_map, not both", key="obs_keys")


@dataclass(frozen=True)
class _Plan:
    """What to read from every demo, decided once for the whole file."""

    layout: str  # robomimic | robosuite | key_map
    action_path: str  # its length is the episode length T
    keys: dict[str, str]  # dataset key -> path inside the demo group
    skipped: dict[str, str]  # path -> why it is not read


def options_from_dict(data: dict | None, *, source: str | None = None) -> Hdf5Options:
    """Hdf5Options from a config mapping; an unknown key is a ConfigError."""
    return from_dict(Hdf5Options, data or {}, source=source)


def read_hdf5(path: str | Path, options: Hdf5Options | None = None) -> Recording:
    """Open a robomimic / robosuite HDF5 file; episodes are read lazily, one demo at a time."""
    options = options or Hdf5Options()
    file = str(path)
    with _open(file) as f:
        data = _data_group(f, file)
        all_demos = _demo_names(data, file)
        masks = _masks(f)
        demos = _select_demos(all_demos, masks, options.filter_key, file)
        plan = _plan(data, demos, options)
        meta = _file_meta(data, all_demos, demos, masks, plan, options)
    return Recording(meta=meta, episodes=_episodes(file, demos, masks, plan))


# ----------------------------------------------------------------------------- file structure

def _open(file: str) -> h5py.File:
    if not Path(file).is_file():
        raise SefaInputError("file not found", file=file)
    try:
        return h5py.File(file, "r")
    except OSError as e:
        # h5py says "truncated file" or "file signature not found"; keep its reason
        raise SefaInputError(f"not a readable HDF5 file ({_first_line(e)})", file=file) from None


def _first_line(e: BaseException) -> str:
    return str(e).splitlines()[0] if str(e) else type(e).__name__


def _data_group(f: h5py.File, file: str) -> h5py.Group:
    data = f.get("data")
    if not isinstance(data, h5py.Group):
        raise SefaInputError(f"no 'data' group (top level has: {_listing(f)})", file=file)
    return data


def _listing(group: h5py.Group) -> str:
    return ", ".join(sorted(group.keys())) or "nothing"


def _demo_names(data: h5py.Group, file: str) -> list[str]:
    """Demo groups ordered by their integer suffix: demo_10 comes after demo_9, gaps allowed."""
    demos = [name for name in data.keys()
             if _DEMO_NAME.fullmatch(name) and isinstance(data[name], h5py.Group)]
    if not demos:
        raise SefaInputError(f"no demo_N groups under 'data' (it has: {_listing(data)})",
                             file=file, key="data")
    return sorted(demos, key=lambda name: int(name[len("demo_"):]))


def _masks(f: h5py.File) -> dict[str, set[str]]:
    """robomimic filter keys: mask/<name> lists demo names (stored as bytes)."""
    group = f.get("mask")
    if not isinstance(group, h5py.Group):
        return {}
    return {name: {_text(x) for x in np.asarray(ds[()]).ravel()}
            for name, ds in group.items() if isinstance(ds, h5py.Dataset)}


def _text(value: object) -> str:
    return value.decode() if isinstance(value, bytes) else str(value)


def _select_demos(demos: list[str], masks: dict[str, set[str]], filter_key: str | None,
                  file: str) -> list[str]:
    if filter_key is None:
        return demos
    if filter_key not in masks:
        have = ", ".join(sorted(masks)) or "none (the file has no mask group)"
        raise SefaInputError(f"unknown filter key '{filter_key}'; available: {have}", file=file,
                             key="mask")
    missing = sorted(masks[filter_key] - set(demos), key=_demo_order)
    if missing:
        raise SefaInputError(f"lists demos that are not in 'data': {', '.join(missing)}",
                             file=file, key=f"mask/{filter_key}")
    if not masks[filter_key]:
        raise SefaInputError("lists no demos", file=file, key=f"mask/{filter_key}")
    return [d for d in demos if d in masks[filter_key]]


# ----------------------------------------------------------------------------- the read plan

def _plan(data: h5py.Group, demos: list[str], options: Hdf5Options) -> _Plan:
    first = data[demos[0]]
    if options.key_map:
        action = options.key_map.get("action", options.action_key)
        return _Plan("key_map", action, dict(options.key_map), {})
    if isinstance(first.get("obs"), h5py.Group) or options.obs_keys is not None:
        layout = "robomimic"
        explicit, optional = _robomimic_keys(data, demos, options)
    else:
        layout = "robosuite"
        explicit, optional = _robosuite_keys(data, demos, options)
    kept, skipped = _keep_consistent(data, demos, options.action_key, optional)
    return _Plan(layout, options.action_key, {**explicit, **kept}, skipped)


def _robomimic_keys(data: h5py.Group, demos: list[str],
                    options: Hdf5Options) -> tuple[dict[str, str], dict[str, str]]:
    """(keys every demo must have, keys read only where every demo has them)."""
    explicit = {"action": options.action_key}
    optional: dict[str, str] = {}
    if options.obs_keys is not None:
        explicit.update({f"observation.{k}": f"obs/{k}" for k in options.obs_keys})
    else:
        names = _union(data, demos, lambda g: _dataset_paths(g.get("obs")))
        optional.update({f"observation.{n}": f"obs/{n}" for n in names})
    if options.include_rewards:
        optional.update({"reward": "rewards", "done": "dones"})
    return explicit, optional


def _robosuite_keys(data: h5py.Group, demos: list[str],
                    options: Hdf5Options) -> tuple[dict[str, str], dict[str, str]]:
    canonical = {"states": "state", "rewards": "reward", "dones": "done"}
    ignored = {options.action_key} | (set() if options.include_rewards else {"rewards", "dones"})
    paths = [p for p in _union(data, demos, _dataset_paths) if p not in ignored]
    # the well-known streams first, then the others under their path with dots
    optional = {canonical[p]: p for p in canonical if p in paths}
    optional.update({p.replace("/", "."): p for p in paths if p not in canonical})
    return {"action": options.action_key}, optional


def _dataset_paths(group: h5py.Group | None) -> list[str]:
    """Paths of every dataset below `group`, relative to it, in the file's order."""
    if not isinstance(group, h5py.Group):
        return []
    paths: list[str] = []
    group.visititems(lambda name, obj: paths.append(name) if isinstance(obj, h5py.Dataset)
                     else None)
    return paths


def _union(data: h5py.Group, demos: list[str],
           paths_of: Callable[[h5py.Group], list[str]]) -> list[str]:
    seen: dict[str, None] = {}  # an ordered set: keys keep the first demo's order
    for demo in demos:
        seen.update(dict.fromkeys(paths_of(data[demo])))
    return list(seen)


def _keep_consistent(data: h5py.Group, demos: list[str], action_path: str,
                     optional: dict[str, str]) -> tuple[dict[str, str], dict[str, str]]:
    """Split optional keys into those with one row per action, a numeric dtype and one frame
    shape in every demo (read), and the rest (skipped, with the first reason found)."""
    kept: dict[str, str] = {}
    skipped: dict[str, str] = {}
    for key, path in optional.items():
        reason = _why_not(data, demos, action_path, path)
        if reason is None:
            kept[key] = path
        else:
            skipped[path] = reason
    return kept, skipped


def _why_not(data: h5py.Group, demos: list[str], action_path: str, path: str) -> str | None:
    seen: tuple[np.dtype, tuple[int, ...], str] | None = None
    for demo in demos:
        group = data[demo]
        ds, action = group.get(path), group.get(action_path)
        if not isinstance(action, h5py.Dataset):
            continue  # the iterator reports the missing action when it reaches this demo
        if not isinstance(ds, h5py.Dataset):
            return f"missing in {demo}"
        if ds.dtype.kind not in _NUMERIC_KINDS or ds.ndim == 0:
            return f"not a numeric per-step array ({ds.dtype}, shape {ds.shape})"
        if ds.shape[0] != action.shape[0]:
            return f"{ds.shape[0]} rows for {action.shape[0]} actions in {demo}"
        if seen is not None and (ds.dtype, ds.shape[1:]) != seen[:2]:
            return f"{ds.dtype} {ds.shape[1:]} in {demo} but {seen[0]} {seen[1]} in {seen[2]}"
        seen = seen or (ds.dtype, ds.shape[1:], demo)
    return None


# ----------------------------------------------------------------------------- metadata

def _file_meta(data: h5py.Group, all_demos: list[str], demos: list[str],
               masks: dict[str, set[str]], plan: _Plan, options: Hdf5Options) -> dict:
    attrs = {name: _plain(value) for name, value in data.attrs.items()}
    steps = sum(_rows(data[d], plan.action_path) for d in all_demos)
    warnings: list[str] = []
    meta: dict = {"format": "hdf5", "layout": plan.layout}
    for name in _ENV_ATTRS:
        if name in attrs:
            value = attrs[name]
            meta[name] = _parse_json(name, value, warnings) if name in _JSON_ATTRS else value
    fps = _control_freq(meta)
    if fps is not None:
        meta["fps"] = fps
    total = attrs.get("total")
    if total is not None and total != steps:
        warnings.append(f"data.attrs['total'] is {total} but the demos hold {steps} steps")
    meta.update({
        "total": total,
        "steps": steps,
        "demos": demos,
        "filter_key": options.filter_key,
        "filters": {name: sorted(names, key=_demo_order) for name, names in masks.items()},
        "keys": plan.keys,
        "skipped": plan.skipped,
        "attrs": {k: v for k, v in attrs.items() if k not in (*_ENV_ATTRS, "total")},
        "warnings": warnings,
    })
    return meta


def _control_freq(meta: dict) -> float | None:
    """robosuite applies one action per control step, so its control_freq is the episode rate.
    Taken only when the file records it (the Lift file does not; robosuite's default is not
    guessed)."""
    env_args = meta.get("env_args")
    kwargs = env_args.get("env_kwargs") if isinstance(env_args, dict) else None
    for holder in (kwargs, meta.get("env_info")):
        value = holder.get("control_freq") if isinstance(holder, dict) else None
        if isinstance(value, (int, float)) and not isinstance(value, bool) and value > 0:
            return float(value)
    return None


def _rows(group: h5py.Group, path: str) -> int:
    ds = group.get(path)
    return int(ds.shape[0]) if isinstance(ds, h5py.Dataset) and ds.ndim else 0


def _demo_order(name: str) -> tuple[int, str]:
    match = _DEMO_NAME.fullmatch(name)
    return (int(match.group(1)) if match else -1, name)


def _plain(value: object) -> object:
    """An HDF5 attribute as a JSON-ready Python value."""
    if isinstance(value, bytes):
        return value.decode(errors="replace")
    if isinstance(value, np.ndarray):
        return [_plain(v) for v in value.tolist()]
    if isinstance(value, np.generic):
        return value.item()
    return value


def _parse_json(name: str, value: object, warnings: list[str]) -> object:
    if not isinstance(value, str):
        return value
    try:
        return json.loads(value)
    except json.JSONDecodeError as e:
        warnings.append(f"data.attrs['{name}'] is not valid JSON ({e.msg}); kept as text")
        return value


# ----------------------------------------------------------------------------- episodes

def _episodes(file: str, demos: list[str], masks: dict[str, set[str]],
              plan: _Plan) -> Iterator[Episode]:
    with _open(file) as f:
        data = _data_group(f, file)
        for demo in demos:
            yield Episode(data=_read_demo(data[demo], plan, file), source=file, label=demo,
                          filters={name for name, names in masks.items() if demo in names})


def _read_demo(group: h5py.Group, plan: _Plan, file: str) -> dict[str, np.ndarray]:
    demo = group.name.lstrip("/")  # data/demo_3
    action = group.get(plan.action_path)
    if not isinstance(action, h5py.Dataset):
        raise SefaInputError(f"no action dataset '{plan.action_path}' (the demo has: "
                             f"{_listing(group)})", file=file, key=demo)
    steps = action.shape[0] if action.ndim else 0
    if steps == 0:
        raise SefaInputError("empty demo (0 steps)", file=file, key=f"{demo}/{plan.action_path}")
    # action first: the store and users expect to find it at the top
    paths = {"action": plan.action_path, **plan.keys}
    return {key: _read_key(group, path, steps, file, demo) for key, path in paths.items()}


def _read_key(group: h5py.Group, path: str, steps: int, file: str, demo: str) -> np.ndarray:
    where = f"{demo}/{path}"
    ds = group.get(path)
    if not isinstance(ds, h5py.Dataset):
        raise SefaInputError("missing", file=file, key=where)
    if ds.dtype.kind not in _NUMERIC_KINDS or ds.ndim == 0:
        raise SefaInputError(f"not a numeric per-step array ({ds.dtype}, shape {ds.shape})",
                             file=file, key=where)
    if ds.shape[0] != steps:
        raise SefaInputError(f"{ds.shape[0]} rows but the demo has {steps} actions",
                             file=file, key=where)
    try:
        values = ds[()]
    except OSError as e:  # a truncated or corrupt file can open fine and fail here
        raise SefaInputError(f"cannot read ({_first_line(e)})", file=file, key=where) from None
    bad = first_nonfinite(values)
    if bad is not None:
        raise SefaInputError("NaN or Inf value", file=file, key=where, where=f"step {bad}")
    return values
