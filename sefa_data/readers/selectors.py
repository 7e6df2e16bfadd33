"""Field selectors: the numbers a topic-map feature takes out of one message.

A selector is text from the topic map (`FeatureSpec.field`)::

    ''                                       the whole message, flattened
    pose.pose                                a nested message, flattened (x y z qx qy qz qw)
    twist.twist.linear.x                     one number
    position[lwr_arm_0_joint, lwr_arm_1_joint]
                                             picked by the sibling `name` list, in this order

Messages are rosbags message objects or, for JSON MCAP channels, plain dicts. Flattening walks
fields in definition order (dict insertion order for JSON), skips `header` and strings, and
turns numeric arrays into their elements.

`Selector` parses the text once. It learns the message layout from the first message it is
applied to and turns it into attribute getters, so that applying it to the thousands of
messages that follow is a couple of C-level calls and one numpy conversion.
"""

from __future__ import annotations

import dataclasses
import functools
import operator
import typing
import re
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from sefa_data.errors import SefaInputError

# Where a message keeps its time. It is the stamp source, not data, so flattening skips it.
# `timestamp` is where Foxglove's JSON schemas keep theirs.
STAMP_FIELDS = ("header", "timestamp")

_PICK = re.compile(r"^(?P<path>[^\[\]]*)\[(?P<names>[^\[\]]*)\]$")


@dataclass(frozen=True)
class ParsedSelector:
    path: tuple[str, ...]  # () selects the whole message
    pick: tuple[str, ...] | None = None  # names to pick from the `name` list beside the target

    @property
    def text(self) -> str:
        base = ".".join(self.path)
        return f"{base}[{', '.join(self.pick)}]" if self.pick is not None else base


def parse_selector(text: str, key: str | None = None) -> ParsedSelector:
    """Parse selector text; a malformed one is a `SefaInputError` naming `key`."""
    text = text.strip()
    pick: tuple[str, ...] | None = None
    if "[" in text or "]" in text:
        m = _PICK.match(text)
        if m is None:
            raise SefaInputError(f"selector '{text}' is malformed: a name pick is "
                                 "`field[name_a, name_b]` at the end of the path", key=key)
        text = m["path"].strip()
        pick = tuple(n.strip() for n in m["names"].split(","))
        if not all(pick):
            raise SefaInputError(f"selector '{m.string}' has an empty name in its [...] pick",
                                 key=key)
        if not text:
            raise SefaInputError(f"selector '{m.string}' picks names but names no field "
                                 "(e.g. position[...])", key=key)
    path = tuple(p.strip() for p in text.split(".")) if text else ()
    if any(not p for p in path):
        raise SefaInputError(f"selector '{text}' has an empty path component", key=key)
    return ParsedSelector(path, pick)


# --- what a value is ---------------------------------------------------------------------------

def is_message(obj: Any) -> bool:
    """A rosbags message object (a dataclass instance) or a decoded JSON object."""
    return isinstance(obj, dict) or (dataclasses.is_dataclass(obj) and not isinstance(obj, type))


def type_name(obj: Any) -> str:
    if isinstance(obj, dict):
        return "JSON object"
    return getattr(obj, "__msgtype__", None) or type(obj).__name__


def field_names(obj: Any) -> list[str]:
    """Fields of a message in definition order. Message constants (`uint8 DEBUG=10` in a .msg
    file) are not fields: rosbags declares them, and its `__msgtype__`, as ClassVar dataclass
    fields, which would otherwise flatten into every feature as values that never change."""
    if isinstance(obj, dict):
        return [str(k) for k in obj]
    return _fields_of(type(obj))


@functools.lru_cache(maxsize=None)
def _fields_of(cls: type) -> list[str]:
    return [f.name for f in dataclasses.fields(cls)
            if f.name != "__msgtype__" and not _is_classvar(f.type)]


def _is_classvar(annotation: Any) -> bool:
    if isinstance(annotation, str):
        return annotation.startswith(("ClassVar", "typing.ClassVar"))
    return typing.get_origin(annotation) is typing.ClassVar


def child(obj: Any, name: str) -> Any:
    return obj[name] if isinstance(obj, dict) else getattr(obj, name)


def _is_number(v: Any) -> bool:
    return isinstance(v, (bool, int, float, np.number)) or v is None  # JSON null reads as NaN


# --- flattening --------------------------------------------------------------------------------

@dataclass(frozen=True)
class _Leaf:
    path: tuple[str, ...]  # from the message root
    name: str  # relative to the selected node, e.g. "position.x"
    size: int | None  # None: a scalar; else the element count seen in the first message


def _leaves(obj: Any, path: tuple[str, ...], rel: tuple[str, ...], key: str | None) -> list[_Leaf]:
    """Numeric leaves under `obj` in definition order; strings and stamps are skipped."""
    if is_message(obj):
        out: list[_Leaf] = []
        for name in field_names(obj):
            value = child(obj, name)
            if name in STAMP_FIELDS and is_message(value):
                continue
            out += _leaves(value, path + (name,), rel + (name,), key)
        return out
    label = ".".join(rel) or (path[-1] if path else "value")
    if _is_number(obj):
        return [_Leaf(path, label, None)]
    if isinstance(obj, (str, bytes)):
        return []
    if isinstance(obj, np.ndarray):
        return [_Leaf(path, label, int(obj.size))] if obj.dtype.kind in "biuf" else []
    if isinstance(obj, (list, tuple)):
        if all(isinstance(v, str) for v in obj) and obj:
            return []
        if all(_is_number(v) for v in obj):  # JSON arrays; an empty one is kept and must stay so
            return [_Leaf(path, label, len(obj))]
        raise SefaInputError(f"field '{'.'.join(path)}' is a list of messages, which cannot be "
                             "flattened to a fixed-size vector; select a numeric field", key=key)
    raise SefaInputError(f"field '{'.'.join(path)}' has a value of type {type(obj).__name__}, "
                         "which is not numeric", key=key)


def _leaf_names(leaves: list[_Leaf]) -> list[str]:
    names: list[str] = []
    for leaf in leaves:
        if leaf.size is None:
            names.append(leaf.name)
        else:
            names += [f"{leaf.name}[{i}]" for i in range(leaf.size)]
    return names


# --- getters -----------------------------------------------------------------------------------

def _getter(root: Any, path: tuple[str, ...]) -> Callable[[Any], Any]:
    """A fast accessor for `path`, shaped after the first message (`root`)."""
    if not path:
        return lambda m: m
    if not isinstance(root, dict):
        return operator.attrgetter(".".join(path))  # one C call for the whole dotted path

    def get(m: Any) -> Any:
        for p in path:
            m = m[p]
        return m
    return get


def _tuple_getter(root: Any, paths: list[tuple[str, ...]]) -> Callable[[Any], tuple]:
    if not isinstance(root, dict):
        if len(paths) == 1:
            single = operator.attrgetter(".".join(paths[0]))
            return lambda m: (single(m),)
        return operator.attrgetter(*(".".join(p) for p in paths))
    getters = [_getter(root, p) for p in paths]
    return lambda m: tuple(g(m) for g in getters)


def _resolve(root: Any, path: tuple[str, ...], full: str, key: str | None) -> Any:
    """Walk `path` from `root`, with an error naming the fields that do exist."""
    node = root
    for i, part in enumerate(path):
        if not is_message(node):
            where = ".".join(path[:i])
            raise SefaInputError(f"field '{full}' not found in {type_name(root)}: '{where}' "
                                 "is a value, not a message", key=key)
        names = field_names(node)
        if part not in names:
            inside = f" (inside '{'.'.join(path[:i])}', a {type_name(node)})" if i else ""
            raise SefaInputError(f"field '{full}' not found in {type_name(root)}{inside}; "
                                 f"fields: {', '.join(names)}", key=key)
        node = child(node, part)
    return node


# --- the selector ------------------------------------------------------------------------------

class Selector:
    """A parsed selector; call it on a message to get a 1-D float64 array.

    `names` (one per output dimension) is known after the first call.
    """

    def __init__(self, text: str, key: str | None = None):
        self.parsed = parse_selector(text, key)
        self.key = key
        self.names: list[str] | None = None
        self._apply: Callable[[Any], np.ndarray] | None = None
        # joint picks: the index array is valid while the message's `name` list is unchanged
        self._pick_names: list[str] | None = None
        self._pick_index: np.ndarray | None = None

    def __call__(self, msg: Any) -> np.ndarray:
        if self._apply is None:
            self._apply = self._compile(msg)
        try:
            return self._apply(msg)
        except SefaInputError:
            raise
        except (AttributeError, KeyError, IndexError, TypeError, ValueError) as e:
            # a later message that does not match the first one's layout (JSON mostly)
            raise SefaInputError(f"field '{self.parsed.text}' cannot be read from this "
                                 f"{type_name(msg)}: {type(e).__name__}: {e}", key=self.key
                                 ) from None

    def _compile(self, msg: Any) -> Callable[[Any], np.ndarray]:
        full = self.parsed.text
        target = _resolve(msg, self.parsed.path, full, self.key)
        if self.parsed.pick is not None:
            return self._compile_pick(msg, target)
        rel_root = self.parsed.path[-1:] if not is_message(target) else ()
        leaves = _leaves(target, self.parsed.path, rel_root, self.key)
        if not leaves:
            raise SefaInputError(f"field '{full or '(whole message)'}' of {type_name(msg)} "
                                 "has no numeric values", key=self.key)
        self.names = _leaf_names(leaves)
        fetch = _tuple_getter(msg, [leaf.path for leaf in leaves])
        if all(leaf.size is None for leaf in leaves):
            return lambda m: np.array(fetch(m), dtype=np.float64)
        if len(leaves) == 1:
            return lambda m: np.array(fetch(m)[0], dtype=np.float64).reshape(-1)
        return lambda m: np.concatenate(
            [np.asarray(v, dtype=np.float64).reshape(-1) for v in fetch(m)])

    def _compile_pick(self, msg: Any, target: Any) -> Callable[[Any], np.ndarray]:
        path, pick = self.parsed.path, self.parsed.pick
        assert pick is not None
        parent = path[:-1]
        if "name" not in field_names(_resolve(msg, parent, self.parsed.text, self.key)):
            where = ".".join(parent) or type_name(msg)
            raise SefaInputError(f"selector '{self.parsed.text}' picks by name, but {where} "
                                 "has no `name` list", key=self.key)
        get_values = _getter(msg, path)
        get_names = _getter(msg, parent + ("name",))
        self.names = list(pick)

        def apply(m: Any) -> np.ndarray:
            names = get_names(m)
            if names != self._pick_names:
                self._pick_index = self._index_of(names)
                self._pick_names = names
            values = np.asarray(get_values(m), dtype=np.float64)
            if values.shape != (len(names),):
                raise SefaInputError(f"'{'.'.join(path)}' has {values.size} values for "
                                     f"{len(names)} names", key=self.key)
            return values[self._pick_index]
        return apply

    def _index_of(self, names: list[str]) -> np.ndarray:
        position = {n: i for i, n in enumerate(names)}
        missing = [n for n in self.parsed.pick or () if n not in position]
        if missing:
            raise SefaInputError(f"name '{missing[0]}' of selector '{self.parsed.text}' is not "
                                 f"in the message's name list; available: {', '.join(names)}",
                                 key=self.key)
        return np.array([position[n] for n in self.parsed.pick or ()], dtype=np.intp)


def select(msg: Any, text: str, key: str | None = None) -> tuple[np.ndarray, list[str]]:
    """One-off: the values and dimension names `text` selects from `msg`."""
    sel = Selector(text, key)
    values = sel(msg)
    return values, sel.names or []
