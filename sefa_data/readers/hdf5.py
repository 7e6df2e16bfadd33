"""Read robomimic and robosuite HDF5 demonstrations as episodes.

Three layouts, all with one ``data/demo_N`` group per demonstration:

* ``robomimic``: ``obs/<key>``, ``actions``, ``rewards``, ``dones``, ``mask/<filter>`` and a
  JSON ``env_args`` attribute. Dataset keys: ``action``, ``observation.<key>``, ``reward``,
  ``done``.
* ``robosuite`` (a raw recording, no ``obs/``): ``states`` and ``actions`` become ``state`` and
  ``action``; a demo whose ``states`` is missing or not one row per action is an error naming
  the demo and both lengths (``skip_bad_demos``: that demo is skipped with a warning). Every
  other per-demo stream is read too (``controller_info/robot_controls/action`` becomes
  ``controller_info.robot_controls.action``) when it has one row per action in every demo; the
  rest (the handover file's controller and user logs run at their own rate) is skipped and
  listed in the metadata.
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
from sefa_data.validate import check_fps, check_key, check_memory, key_problem

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
    # a demo where an observation (or reward, done) key is missing, has another length than the
    # actions, or another dtype or frame shape than in the other demos: an error naming the demo
    # and the key; with this, that demo is skipped with a warning instead
    skip_bad_demos: bool = False
    fps: float | None = None  # the store's rate, when the file does not record control_freq

    def validate(self) -> None:
        if self.key_map and self.obs_keys is not None:
            raise ConfigError("give either obs_keys or key_map, not both", key="obs_keys")
        for key in self.key_map:
            check_key(key, error=ConfigError)
        if self.fps is not None:
            try:
                check_fps(self.fps)
            except SefaInputError as e:
                raise ConfigError(e.what, key="fps") from None


@dataclass(frozen=True)
class _Plan:
    """What to read from every demo, decided once for the whole file."""

    layout: str  # robomimic | robosuite | key_map
    action_path: str  # its length is the episode length T
    keys: dict[str, str]  # dataset key -> path inside the demo group
    skipped: dict[str, str]  # path -> why it is not read
    bad_demos: dict[str, str] = field(default_factory=dict)  # demo -> why it is skipped


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
        plan = _plan(data, demos, options, file)
        demos = [d for d in demos if d not in plan.bad_demos]
        if not demos:
            raise SefaInputError("every demo was skipped as bad; nothing to read", file=file)
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

def _plan(data: h5py.Group, demos: list[str], options: Hdf5Options, file: str) -> _Plan:
    first = data[demos[0]]
    if options.key_map:
        action = options.key_map.get("action", options.action_key)
        return _Plan("key_map", action, dict(options.key_map), {})
    if isinstance(first.get("obs"), h5py.Group) or options.obs_keys is not None:
        layout = "robomimic"
        explicit, strict = _robomimic_keys(data, demos, options)
        lenient: dict[str, str] = {}
    else:
        layout = "robosuite"
        explicit, lenient = _robosuite_keys(data, demos, options)
        # `states` is the raw recording's observation: without it in every demo the policy has
        # no input, so a demo where it is missing or of another length is the same error as a
        # robomimic observation's (--skip-bad-demos skips that demo), never the key dropped
        # from every demo; only the side streams (controller and user logs) are left out
        strict = {"state": lenient.pop("state")} if "state" in lenient else {}
    bad_demos = _bad_demos(data, demos, options.action_key, strict, options.skip_bad_demos, file)
    good = [d for d in demos if d not in bad_demos]
    kept, skipped = _keep_consistent(data, good, options.action_key, lenient)
    return _Plan(layout, options.action_key, {**explicit, **strict, **kept}, skipped, bad_demos)


def _robomimic_keys(data: h5py.Group, demos: list[str],
                    options: Hdf5Options) -> tuple[dict[str, str], dict[str, str]]:
    """(keys the user asked for, keys found in the file that every demo must have)."""
    explicit = {"action": options.action_key}
    found: dict[str, str] = {}
    if options.obs_keys is not None:
        explicit.update({f"observation.{k}": f"obs/{k}" for k in options.obs_keys})
    else:
        names = _union(data, demos, lambda g: _dataset_paths(g.get("obs")))
        found.update({f"observation.{n}": f"obs/{n}" for n in names})
    if options.include_rewards:
        present = set(_union(data, demos, _dataset_paths))
        found.update({k: p for k, p in (("reward", "rewards"), ("done", "dones")) if p in present})
    return explicit, found


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


def _steps(group: h5py.Group, action_path: str) -> int | None:
    """The demo's length T, or None when its action is not a numeric per-step array (the
    iterator reports that when it reaches the demo)."""
    action = group.get(action_path)
    if not isinstance(action, h5py.Dataset) or action.ndim == 0 \
            or action.dtype.kind not in _NUMERIC_KINDS:
        return None
    return int(action.shape[0])


def _problem(ds: object, steps: int) -> str | None:
    """Why `ds` is not a numeric array with one row per action, or None."""
    if not isinstance(ds, h5py.Dataset):
        return "missing"
    if ds.dtype.kind not in _NUMERIC_KINDS or ds.ndim == 0:
        return f"not a numeric per-step array ({ds.dtype}, shape {ds.shape})"
    if ds.shape[0] != steps:
        return f"{ds.shape[0]} rows for {steps} actions"
    return None


def _bad_demos(data: h5py.Group, demos: list[str], action_path: str, strict: dict[str, str],
               skip: bool, file: str) -> dict[str, str]:
    """Demos where a key that every demo must carry is missing, of another length than the
    actions, or of another dtype or frame shape than in the first demo that has it. Without
    `skip` the first one is an error naming the demo and the key: dropping the key from every
    demo, or the demo, silently would lose data."""
    reference: dict[str, tuple[np.dtype, tuple[int, ...], str]] = {}
    bad: dict[str, str] = {}
    for demo in demos:  # in demo order, so that the error names the first bad demo
        group = data[demo]
        steps = _steps(group, action_path)
        if steps is None:
            continue
        for path in strict.values():
            ds = group.get(path)
            why = _problem(ds, steps)
            seen = reference.get(path)
            if why is None and seen is not None and (ds.dtype, ds.shape[1:]) != seen[:2]:
                why = f"{ds.dtype} {ds.shape[1:]} where {seen[2]} has {seen[0]} {seen[1]}"
            if why is None:
                reference.setdefault(path, (ds.dtype, ds.shape[1:], demo))
                continue
            if not skip:
                raise SefaInputError(f"{why} (every demo needs it; --skip-bad-demos skips such "
                                     "demos with a warning)", file=file,
                                     key=f"data/{demo}/{path}")
            bad[demo] = f"data/{demo}/{path}: {why}"
            break
    return bad


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
        steps = _steps(group, action_path)
        if steps is None:
            continue
        ds = group.get(path)
        why = _problem(ds, steps)
        if why is not None:
            return f"{why} in {demo}" if why != "missing" else f"missing in {demo}"
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
    fps = options.fps if options.fps is not None else _control_freq(meta)
    if fps is not None:
        meta["fps"] = fps
    total = attrs.get("total")
    if total is not None and total != steps:
        warnings.append(f"data.attrs['total'] is {total} but the demos hold {steps} steps")
    for demo, why in plan.bad_demos.items():
        warnings.append(f"skipped demo {demo} (--skip-bad-demos): {why}")
    if options.filter_key is not None:
        left_out = len(all_demos) - len(demos) - len(plan.bad_demos)
        if left_out:
            warnings.append(f"{left_out} of {len(all_demos)} demos are not in "
                            f"mask/{options.filter_key} and are not read")
    meta.update({
        "total": total,
        "steps": steps,
        "demos": demos,
        "filter_key": options.filter_key,
        "filters": {name: sorted(names, key=_demo_order) for name, names in masks.items()},
        "keys": plan.keys,
        "skipped": plan.skipped,
        "skipped_demos": plan.bad_demos,
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
        if value is not None:
            try:
                return check_fps(value)
            except SefaInputError:
                continue  # not a usable rate: the user gives --fps
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
    if action.ndim == 0 or action.dtype.kind not in _NUMERIC_KINDS:
        raise SefaInputError(f"actions must be numbers with one row per step; this is "
                             f"{'a single ' if action.ndim == 0 else ''}{action.dtype} "
                             f"{'value' if action.ndim == 0 else f'of shape {action.shape}'}",
                             file=file, key=f"{demo}/{plan.action_path}")
    steps = action.shape[0]
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
    check_memory(ds.size * ds.dtype.itemsize, f"reading {ds.shape} {ds.dtype}", file=file,
                 key=where)
    try:
        values = ds[()]
    except OSError as e:  # a truncated or corrupt file can open fine and fail here
        raise SefaInputError(f"cannot read ({_first_line(e)})", file=file, key=where) from None
    bad = first_nonfinite(values)
    if bad is not None:
        raise SefaInputError("NaN or Inf value", file=file, key=where, where=f"step {bad}")
    return values


# ----------------------------------------------------------------------------- inspect, scaffold

def _survey(data: h5py.Group, demos: list[str], action_path: str) -> dict[str, dict]:
    """Per dataset path (union over demos): dtype and frame shape in the first demo that has it,
    how many demos have it, and why it is not a per-step stream, if it is not."""
    out: dict[str, dict] = {}
    for path in _union(data, demos, _dataset_paths):
        first = next(data[d][path] for d in demos if isinstance(data[d].get(path), h5py.Dataset))
        out[path] = {"dtype": str(first.dtype), "shape": list(first.shape[1:]) if first.ndim else [],
                     "demos": sum(isinstance(data[d].get(path), h5py.Dataset) for d in demos),
                     "per_step": path == action_path or _why_not(data, demos, action_path, path)
                     is None,
                     "why_not": None if path == action_path
                     else _why_not(data, demos, action_path, path)}
    return out


def inspect_hdf5(path: str | Path) -> dict:
    """What an HDF5 file holds and what `sefa ingest` reads from it with default options."""
    file = str(path)
    with _open(file) as f:
        data = _data_group(f, file)
        demos = _demo_names(data, file)
        masks = _masks(f)
        lengths = [_rows(data[d], "actions") for d in demos]
        datasets = _survey(data, demos, "actions")
        try:
            plan = _plan(data, demos, Hdf5Options(), file)
            reads, problem = {"action": plan.action_path, **plan.keys}, None
            skipped = plan.skipped
        except SefaInputError as e:
            reads, problem, skipped = {}, e.what, {}
        attrs = {name: _plain(value) for name, value in data.attrs.items()}
        meta = {n: attrs[n] for n in _ENV_ATTRS if n in attrs}
    env_args = meta.get("env_args")
    return {
        "path": file,
        "format": "hdf5",
        "layout": "robomimic" if any("obs/" in p for p in datasets) else "robosuite",
        "n_demos": len(demos),
        "steps": sum(lengths),
        "demo_length": {"min": min(lengths), "max": max(lengths),
                        "mean": sum(lengths) / len(lengths)} if lengths else {},
        "masks": {name: len(names) for name, names in masks.items()},
        "env": env_args if isinstance(env_args, str) else meta.get("env"),
        "datasets": datasets,
        "reads": reads,
        "skips": skipped,
        "problem": problem,  # why a plain `sefa ingest` of this file fails, if it does
    }


_CANONICAL = {"actions": "action", "rewards": "reward", "dones": "done", "states": "state"}


def _dataset_key(path: str) -> str:
    if path in _CANONICAL:
        return _CANONICAL[path]
    if path.startswith("obs/"):
        return "observation." + path[len("obs/"):].replace("/", ".")
    return path.replace("/", ".")


def scaffold_key_map(path: str | Path, fps: float | None = None) -> str:
    """A commented starter HDF5 key map (YAML for `sefa ingest FILE --map MAP.yaml`): every
    dataset with one row per action in every demo, and why each other dataset is left out."""
    file = str(path)
    with _open(file) as f:
        data = _data_group(f, file)
        demos = _demo_names(data, file)
        all_paths = _union(data, demos, _dataset_paths)
        action = "actions" if "actions" in all_paths else next(
            (p for p in all_paths if "action" in p.rsplit("/", 1)[-1].lower()
             and all(_steps(data[d], p) for d in demos)), None)
        if action is None or not all(_steps(data[d], action) for d in demos):
            raise SefaInputError("no numeric action dataset found in every demo (looked for "
                                 "'actions' and names containing 'action'); datasets: "
                                 + ", ".join(all_paths[:20]), file=file)
        survey = _survey(data, demos, action)
        attrs = {name: _plain(value) for name, value in data.attrs.items()}
        meta = {n: _parse_json(n, attrs[n], []) if n in _JSON_ATTRS else attrs[n]
                for n in _ENV_ATTRS if n in attrs}
    rate = fps if fps is not None else _control_freq(meta)
    out = [f"# sefa HDF5 key map scaffolded from {Path(file).name} "
           f"({len(demos)} demos): sefa ingest {Path(file).name} --map THIS.yaml",
           "# Each entry is dataset key: path inside every data/demo_N group. Rename the keys to",
           "# what your policy expects and delete what you do not need.",
           f"fps: {rate:g}" + ("" if fps is not None else "  # the file's control_freq")
           if rate is not None else
           "# fps: 20  # the file does not record its rate: set it here or give --fps",
           "key_map:"]
    taken: set[str] = set()
    left_out = []
    for p, info in survey.items():
        if p.startswith("next_obs/"):
            left_out.append(f"#   {p}: next_obs repeats obs one step later")
            continue
        if not info["per_step"]:
            left_out.append(f"#   {p}: {info['why_not']}")
            continue
        key = "action" if p == action else _dataset_key(p)
        if key_problem(key) is not None:
            key = _slug_key(key)
        out.append(f"  {json.dumps(_unique_key(key, taken))}: {json.dumps(p)}"
                   f"  # {info['dtype']} {tuple(info['shape'])}")
    if left_out:
        out += ["# Not mapped (not one row per action in every demo):", *left_out]
    return "\n".join(out) + "\n"


def _slug_key(key: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.]+", "_", key).strip("._") or "key"


def _unique_key(key: str, taken: set[str]) -> str:
    out, n = key, 2
    while out in taken:
        out, n = f"{key}_{n}", n + 1
    taken.add(out)
    return out
