"""Typed dataclass configs from YAML or dicts, with strict keys and `key=value` overrides.

Every config in sefa goes through `from_dict`: an unknown key is an error that names the nearest
valid key, and values are checked against the field's annotation. No value is ever evaluated as
code.
"""

from __future__ import annotations

import dataclasses
import difflib
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

import yaml

from sefa_data.errors import ConfigError
from sefa_data.ranges import check_ranges

T = TypeVar("T")


def _suggest(key: str, valid: list[str]) -> str:
    close = difflib.get_close_matches(key, valid, n=1, cutoff=0.5)
    return f"; did you mean '{close[0]}'?" if close else f"; valid keys: {', '.join(sorted(valid))}"


def _convert(value: Any, tp: Any, where: str, source: str | None) -> Any:
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if tp is Any:
        return value
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _convert(value, arg, where, source)
            except ConfigError as e:
                errors.append(e.what)
        raise ConfigError(errors[0] if errors else f"invalid value {value!r}", file=source, key=where)
    if origin is typing.Literal:
        if value not in args:
            raise ConfigError(f"must be one of {', '.join(map(repr, args))}, got {value!r}",
                              file=source, key=where)
        return value
    if dataclasses.is_dataclass(tp):
        if isinstance(value, tp):
            return value
        if not isinstance(value, dict):
            raise ConfigError(f"expected a mapping, got {type(value).__name__}", file=source, key=where)
        return from_dict(tp, value, source=source, prefix=where)
    if origin is list:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"expected a list, got {value!r}", file=source, key=where)
        (item,) = args or (Any,)
        return [_convert(v, item, f"{where}[{i}]", source) for i, v in enumerate(value)]
    if origin is dict:
        if not isinstance(value, dict):
            raise ConfigError(f"expected a mapping, got {value!r}", file=source, key=where)
        kt, vt = args or (Any, Any)
        return {_convert(k, kt, where, source): _convert(v, vt, f"{where}.{k}", source)
                for k, v in value.items()}
    if tp is bool:
        if isinstance(value, bool):
            return value
        raise ConfigError(f"expected true or false, got {value!r}", file=source, key=where)
    if tp is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
        if isinstance(value, str):  # PyYAML reads `1e-4` (no dot) as a string
            try:
                return float(value)
            except ValueError:
                pass
        raise ConfigError(f"expected a number, got {value!r}", file=source, key=where)
    if tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        raise ConfigError(f"expected an integer, got {value!r}", file=source, key=where)
    if tp is str:
        if isinstance(value, str):
            return value
        raise ConfigError(f"expected a string, got {value!r}", file=source, key=where)
    return value


def from_dict(cls: type[T], data: dict[str, Any], *, source: str | None = None,
              prefix: str = "") -> T:
    """Build dataclass `cls` from `data`; unknown keys and ill-typed values raise ConfigError."""
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"expected a mapping, got {type(data).__name__}", file=source,
                          key=prefix or None)
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    kwargs = {}
    for key, value in data.items():
        where = f"{prefix}.{key}" if prefix else str(key)
        if key not in fields:
            raise ConfigError(f"unknown key '{key}'{_suggest(str(key), list(fields))}",
                              file=source, key=prefix or None)
        kwargs[key] = _convert(value, hints[key], where, source)
    missing = [n for n, f in fields.items() if n not in kwargs
               and f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING]
    if missing:
        raise ConfigError(f"missing required key '{missing[0]}'", file=source, key=prefix or None)
    obj = cls(**kwargs)
    check_ranges(obj, prefix, source)
    check = getattr(obj, "validate", None)
    if check is not None:
        try:
            check()
        except ConfigError as e:
            key = f"{prefix}.{e.key}" if prefix and e.key else e.key or prefix or None
            raise ConfigError(e.what, file=source, key=key) from None
    return obj


def to_dict(obj: Any) -> Any:
    """A plain JSON/YAML-ready copy of a (nested) dataclass config."""
    return dataclasses.asdict(obj) if dataclasses.is_dataclass(obj) else obj


class _StrictLoader(yaml.SafeLoader):
    """PyYAML's safe loader, but a key given twice in one mapping is an error: safe_load keeps
    the last silently, so a map with two entries for one feature would mean only one of them."""


def _strict_mapping(loader: _StrictLoader, node: yaml.MappingNode) -> dict:
    loader.flatten_mapping(node)
    seen: dict = {}
    for key_node, _ in node.value:
        key = loader.construct_object(key_node, deep=True)
        if isinstance(key, (str, int, float, bool)) and key in seen:
            raise yaml.constructor.ConstructorError(
                None, None, f"key {key!r} appears twice in one mapping (first at line "
                f"{seen[key] + 1})", key_node.start_mark)
        if isinstance(key, (str, int, float, bool)):
            seen[key] = key_node.start_mark.line
    return loader.construct_mapping(node, deep=True)


_StrictLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _strict_mapping)


def load_yaml(path: str | Path) -> dict[str, Any]:
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise ConfigError("file not found", file=str(path)) from None
    except IsADirectoryError:
        raise ConfigError("is a directory, not a YAML file", file=str(path)) from None
    except UnicodeDecodeError:
        raise ConfigError("not a text file (YAML expected)", file=str(path)) from None
    except OSError as e:
        raise ConfigError(f"cannot read ({e.strerror or e})", file=str(path)) from None
    return parse_yaml(text, str(path))


def parse_yaml(text: str, source: str) -> dict[str, Any]:
    """A YAML mapping as every config file is read (a key twice in one mapping refused)."""
    try:
        data = yaml.load(text, Loader=_StrictLoader)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f"line {mark.line + 1}" if mark is not None else None
        raise ConfigError(f"not valid YAML: {getattr(e, 'problem', e)}", file=source,
                          where=where) from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError("expected a mapping at the top level", file=source)
    return data


def parse_value(raw: str, key: str) -> Any:
    """One `key=value` value, as YAML (never code); text that is not YAML is one line."""
    if raw == "":
        return ""
    try:
        return yaml.safe_load(raw)
    except yaml.YAMLError as e:
        raise ConfigError(f"{raw!r} is not a YAML value ({getattr(e, 'problem', None) or e}; "
                          "quote text, write lists as [1, 2])", key=key) from None


def apply_overrides(data: dict[str, Any], overrides: list[str]) -> dict[str, Any]:
    """Apply Hydra-style `a.b=value` overrides; values are parsed as YAML scalars, never code."""
    out = dict(data)
    for item in overrides:
        if "=" not in item:
            raise ConfigError(f"override '{item}' is not of the form key=value")
        dotted, raw = item.split("=", 1)
        value = parse_value(raw, dotted)
        node = out
        parts = dotted.split(".")
        for part in parts[:-1]:
            child = node.get(part)
            child = dict(child) if isinstance(child, dict) else {}
            node[part] = child
            node = child
        node[parts[-1]] = value
    return out
