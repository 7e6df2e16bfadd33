"""The site's reference pages, generated from the code so that they cannot drift from it.

- docs/reference/commands.md: every command of the `sefa` CLI (the typer app `sefa_cli.main.app`,
  read through click, which typer builds on): its usage, help, arguments and options with their
  types and defaults.
- docs/reference/settings.md: every field of the typed settings files (the train config, the
  workspace's sefa.yaml, a ROS/MCAP topic map, an HDF5 key map): its key as typed, its type,
  its default, the valid range the code checks (`sefa_data.ranges.knob`) and the comment the
  code gives it.

Run by the MkDocs hook (docs/hooks.py) on every `mkdocs build`/`serve`, and by hand:

    python scripts/gen_reference.py            # writes both pages
    python scripts/gen_reference.py --check    # exit 1 if a written page is out of date

Written here rather than with mkdocs-click or mkdocstrings: mkdocs-click renders click's help
only (no typer annotations' defaults as the user types them, no sub-apps' rich help), and no
plugin reads the valid ranges the dataclass fields carry in their metadata.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import importlib
import inspect
import io
import sys
import textwrap
import tokenize
import typing
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "docs" / "reference"

# The settings files a user writes, each with its root dataclass (module, class name), where it
# is read and the prefix its keys are typed with.
SETTINGS = [
    ("Train config", "sefa_model.config", "TrainConfig",
     "A training YAML (`sefa train FILE.yaml`, `sefa train --preset NAME`, `train_config:` in "
     "sefa.yaml) and the "
     "`key=value` overrides after it (`sefa train training.max_steps=2000`, `train:` in "
     "sefa.yaml, a stage's `train_overrides`)."),
    ("Workspace settings (sefa.yaml)", "sefa_pipelines.stages", "PipelineConfig",
     "`WORKSPACE/sefa.yaml`, a pipeline file (`sefa run PIPELINE.yaml`) or preset "
     "(`sefa run --preset NAME`), "
     "`sefa config set KEY VALUE`."),
    ("Topic map (ROS bags, MCAP)", "sefa_data.readers.topic_map", "TopicMap",
     "`sefa ingest RECORDING --map MAP.yaml`; `--scaffold` writes a starter map."),
    ("HDF5 key map", "sefa_data.readers.hdf5", "Hdf5Options",
     "`sefa ingest FILE.hdf5 --map KEYS.yaml` for HDF5 layouts other than robomimic's; "
     "`--scaffold` writes a starter map."),
]


# --- commands --------------------------------------------------------------------------------

def root_command():
    """The click group behind `sefa` (typer builds it from `sefa_cli.main.app`)."""
    import typer

    from sefa_cli.main import app

    return typer.main.get_command(app)


def _context(cmd, name: str):
    """A click context for `cmd` (typer >= 0.29 vendors its own click: take the command's
    own context class rather than importing click)."""
    return cmd.context_class(cmd, info_name=name)


def walk_commands(group, path=("sefa",)):
    """(path, command) of every leaf command, in the order `sefa --help` lists them."""
    ctx = _context(group, path[-1])
    for name in group.list_commands(ctx):
        cmd = group.get_command(ctx, name)
        if cmd is None or getattr(cmd, "hidden", False):
            continue
        if hasattr(cmd, "list_commands"):
            yield from walk_commands(cmd, (*path, name))
        else:
            yield (*path, name), cmd


def _is_flag(param) -> bool:
    return bool(getattr(param, "is_flag", False))


def _default_text(param) -> str:
    if _is_flag(param):
        return "on" if param.default else "off"
    default = param.default
    if default is None or default == () or default == [] or callable(default):
        return ""
    if isinstance(default, (list, tuple)):
        return ", ".join(map(str, default))
    if hasattr(default, "value") and hasattr(type(default), "__members__"):  # an Enum
        return str(default.value)
    return str(default)


def _annotation_words(annotation) -> str:
    """`Optional[int]` -> integer, `list[Path]` -> path (repeatable), `Literal` -> choices."""
    args = [a for a in typing.get_args(annotation) if a is not type(None)]
    origin = typing.get_origin(annotation)
    if origin is typing.Literal:
        return " | ".join(map(str, typing.get_args(annotation)))
    if origin in (list, tuple):
        return f"{_annotation_words(args[0])}, repeatable" if args else "list"
    if args and origin is not None:  # Optional[X], X | None
        return _annotation_words(args[0]) if len(args) == 1 else " or ".join(
            _annotation_words(a) for a in args)
    if isinstance(annotation, type) and hasattr(annotation, "__members__"):  # an Enum
        return " | ".join(str(m.value) for m in annotation)
    names = {bool: "flag", int: "integer", float: "number", str: "text"}
    if annotation in names:
        return names[annotation]
    return getattr(annotation, "__name__", str(annotation)).lower()


def _type_text(param) -> str:
    if _is_flag(param):
        return "flag"
    descriptor = getattr(param, "type_descriptor", None)
    if descriptor is not None:  # typer >= 0.29
        text = _annotation_words(descriptor.annotation)
    else:  # older typer: a click ParamType
        choices = getattr(param.type, "choices", None)
        text = " | ".join(map(str, choices)) if choices else param.type.name
        if getattr(param, "multiple", False):
            text += ", repeatable"
    lo, hi = getattr(param, "min", None), getattr(param, "max", None)
    if lo is not None or hi is not None:
        text += f" ({'>= ' + str(lo) if lo is not None else ''}"\
                f"{', ' if lo is not None and hi is not None else ''}"\
                f"{'<= ' + str(hi) if hi is not None else ''})"
    if getattr(param, "param_type_name", "") == "argument" and param.nargs == -1 \
            and "repeatable" not in text:
        text += ", one or more"
    return text


def _prose(text: str) -> str:
    """Help text as Markdown shows it as typed: outside `code`, `<run id>` is no HTML tag and
    `*` no emphasis."""
    parts = str(text).split("`")
    for i in range(0, len(parts), 2):  # the even parts are outside code spans
        parts[i] = (parts[i].replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")
                    .replace("*", "\\*"))
    return "`".join(parts)


def _cell(text: str) -> str:
    """One table cell: one line, its pipes escaped."""
    return _prose(" ".join(str(text).split())).replace("|", "\\|")


def command_rows(cmd) -> list[tuple[str, str, str, str]]:
    """(names, type, default, help) of each argument and option, help options left out."""
    rows = []
    for p in cmd.params:
        if getattr(p, "param_type_name", "") == "argument":
            names = f"`{p.name.upper()}`" + ("" if p.required else " (optional)")
        else:
            names = ", ".join(f"`{o}`" for o in [*p.opts, *p.secondary_opts])
        rows.append((names, _type_text(p), _default_text(p), getattr(p, "help", "") or ""))
    return rows


def command_usage(path, cmd) -> str:
    """`sefa ingest [OPTIONS] INPUTS...`, as --help writes it."""
    pieces = [*path, "[OPTIONS]"]
    for p in cmd.params:
        if getattr(p, "param_type_name", "") == "argument":
            name = p.name.upper() + ("..." if p.nargs == -1 else "")
            pieces.append(name if p.required else f"[{name}]")
    return " ".join(pieces)


def commands_page() -> str:
    group = root_command()
    lines = ["# Commands", "",
             "<!-- generated by scripts/gen_reference.py from sefa_cli.main.app: do not edit -->", "",
             "Every `sefa` command with its arguments and options, read from the command line "
             "interface itself (`sefa COMMAND --help` prints the same). Every command also takes "
             "`-h`/`--help`. `sefa --version` prints the version.", ""]
    commands = list(walk_commands(group))
    for path, _ in commands:
        name = " ".join(path)
        lines.append(f"- [`{name}`](#{_anchor(name)})")
    lines.append("")
    for path, cmd in commands:
        name = " ".join(path)
        lines += [f"## {name}", "", "```text", command_usage(path, cmd), "```", ""]
        help_text = inspect.cleandoc(cmd.help or "")
        if help_text:
            lines += [_prose(help_text), ""]
        if getattr(cmd, "context_settings", {}).get("allow_extra_args"):
            lines += ["Takes further arguments after the options (see the usage above).", ""]
        rows = command_rows(cmd)
        if rows:
            lines += ["| argument or option | type | default | what it does |",
                      "|---|---|---|---|"]
            lines += [f"| {n} | {_cell(t)} | {_cell(d)} | {_cell(h)} |" for n, t, d, h in rows]
            lines.append("")
    return "\n".join(lines)


def _anchor(title: str) -> str:
    """The id MkDocs' toc extension gives a heading (lower case, spaces to '-', the rest
    dropped)."""
    out = "".join(c for c in title.lower() if c.isalnum() or c in " -_")
    return "-".join(out.split())


# --- settings --------------------------------------------------------------------------------

def field_comments(cls) -> dict[str, str]:
    """The comment the source gives each field of dataclass `cls`: the comment lines right
    above it and the comment at the end of its line(s)."""
    try:
        source = textwrap.dedent(inspect.getsource(cls))
    except (OSError, TypeError):
        return {}
    comments: dict[int, str] = {}
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type == tokenize.COMMENT:
            comments[tok.start[0]] = tok.string.lstrip("#").strip()
    lines = source.splitlines()
    out = {}
    body = ast.parse(source).body[0].body
    for node in body:
        if not (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name)):
            continue
        above = []
        n = node.lineno - 1
        while n >= 1 and lines[n - 1].strip().startswith("#"):
            above.insert(0, comments.get(n, ""))
            n -= 1
        inline = [comments[i] for i in range(node.lineno, node.end_lineno + 1)
                  if i in comments and not lines[i - 1].strip().startswith("#")]
        out[node.target.id] = " ".join(p for p in [*above, *inline] if p)
    return out


def _annotation_texts(cls) -> dict[str, str]:
    """Each field's annotation as written in the source (`int | None`, `Literal[...]`)."""
    try:
        tree = ast.parse(textwrap.dedent(inspect.getsource(cls)))
    except (OSError, TypeError):
        return {}
    return {n.target.id: ast.unparse(n.annotation) for n in tree.body[0].body
            if isinstance(n, ast.AnnAssign) and isinstance(n.target, ast.Name)}


def _type_words(text: str, hint) -> str:
    if typing.get_origin(hint) is typing.Literal:
        return "one of " + ", ".join(f"`{a}`" for a in typing.get_args(hint))
    args = typing.get_args(hint)
    if type(None) in args and len(args) == 2:  # Optional[Literal[...]]: say its values
        inner = next(a for a in args if a is not type(None))
        if typing.get_origin(inner) is typing.Literal:
            return _type_words(text, inner) + " or `null`"
    return f"`{text.replace(' | ', ' or ')}`"


def _default_of(f: dataclasses.Field) -> str:
    if f.default is not dataclasses.MISSING:
        value = f.default
    elif f.default_factory is not dataclasses.MISSING:
        value = f.default_factory()
        if dataclasses.is_dataclass(value):
            return "(section)"
    else:
        return "required"
    if value is None:
        return "`null`"
    if isinstance(value, bool):
        return f"`{str(value).lower()}`"
    if isinstance(value, str):
        return f"`{value}`" if value else '`""`'
    return f"`{value}`"


def _dict_value_dataclass(hint):
    """The dataclass of a `dict[str, X]` field's values, else None."""
    if typing.get_origin(hint) is dict:
        args = typing.get_args(hint)
        if len(args) == 2 and dataclasses.is_dataclass(args[1]):
            return args[1]
    return None


def _nested_dataclass(hint):
    if dataclasses.is_dataclass(hint):
        return hint
    for arg in typing.get_args(hint):  # Optional[Section]
        if dataclasses.is_dataclass(arg):
            return arg
    return None


def setting_rows(cls, prefix: str = ""):
    """(key, type, default, valid range, comment) of every field of dataclass `cls`, nested
    sections and per-key maps flattened to dotted keys (`training.max_steps`,
    `shape_meta.obs.KEY.type`)."""
    hints = typing.get_type_hints(cls)
    texts, comments = _annotation_texts(cls), field_comments(cls)
    for f in dataclasses.fields(cls):
        key = f"{prefix}{f.name}"
        hint = hints[f.name]
        per_key = _dict_value_dataclass(hint)
        nested = None if per_key is not None else _nested_dataclass(hint)
        if nested is not None:
            yield from setting_rows(nested, key + ".")
            continue
        if per_key is not None:
            yield (key, f"a map: one section per key, `{key}.KEY`", _default_of(f), "",
                   comments.get(f.name, ""))
            yield from setting_rows(per_key, key + ".KEY.")
            continue
        valid = f.metadata.get("valid")
        yield (key, _type_words(texts.get(f.name, str(hint)), hint), _default_of(f),
               valid.words() if valid is not None else "", comments.get(f.name, ""))


def _own_doc(cls) -> str:
    """A dataclass's own docstring; '' for the one dataclasses generates (`Name(field, ...)`)."""
    doc = inspect.cleandoc(cls.__doc__ or "")
    return "" if doc.startswith(f"{cls.__name__}(") else doc


def section_docs(cls, prefix: str = ""):
    """(key, docstring) of every nested section (and per-key map) that has its own docstring."""
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        hint = hints[f.name]
        inner = _dict_value_dataclass(hint)
        key = f"{prefix}{f.name}" + (".KEY" if inner is not None else "")
        inner = inner or _nested_dataclass(hint)
        if inner is None:
            continue
        if _own_doc(inner):
            yield key, _own_doc(inner)
        yield from section_docs(inner, key + ".")


def settings_root(module: str, name: str):
    return getattr(importlib.import_module(module), name)


def settings_page() -> str:
    lines = ["# Settings", "",
             "<!-- generated by scripts/gen_reference.py from the typed configs: do not edit -->",
             "",
             "Every key of every settings file, read from the typed dataclasses that parse them. "
             "Unknown keys are errors that name the nearest valid key; a value outside its valid "
             "range is one line naming the key and the range, before any work. `sefa config "
             "show` prints a workspace's settings resolved.", ""]
    for title, _, _, _ in SETTINGS:
        lines.append(f"- [{title}](#{_anchor(title)})")
    lines.append("")
    for title, module, name, where in SETTINGS:
        cls = settings_root(module, name)
        doc = _own_doc(cls)
        lines += [f"## {title}", "", f"Read by: {where}", "",
                  f"Defined by `{cls.__module__}.{cls.__qualname__}`.", ""]
        if doc:
            lines += [_prose(doc), ""]
        lines += ["| key | type | default | valid | what it is |", "|---|---|---|---|---|"]
        for key, type_, default, valid, comment in setting_rows(cls):
            lines.append(f"| `{key}` | {_cell(type_)} | {_cell(default)} | {_cell(valid)} "
                         f"| {_cell(comment)} |")
        lines.append("")
        notes = list(section_docs(cls))
        if notes:
            lines += [f"What the sections of the {title.lower()} mean, as the code says:", ""]
            lines += [f"- `{key}`: {_prose(' '.join(doc.split()))}" for key, doc in notes]
            lines.append("")
    return "\n".join(lines)


# --- writing ---------------------------------------------------------------------------------

def pages() -> dict[str, str]:
    return {"commands.md": commands_page() + "\n", "settings.md": settings_page() + "\n"}


def write(out: Path = OUT) -> list[Path]:
    """Write the pages whose text changed (an unchanged page keeps its mtime, so that
    `mkdocs serve` does not rebuild in a loop); the paths written."""
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for name, text in pages().items():
        path = out / name
        if not path.exists() or path.read_text() != text:
            path.write_text(text)
            written.append(path)
    return written


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true",
                        help="exit 1 if a written page differs from the code's")
    args = parser.parse_args(argv)
    if args.check:
        stale = [name for name, text in pages().items()
                 if not (OUT / name).exists() or (OUT / name).read_text() != text]
        for name in stale:
            print(f"docs/reference/{name} is out of date: run python scripts/gen_reference.py",
                  file=sys.stderr)
        return 1 if stale else 0
    for path in write():
        print(f"wrote {path.relative_to(REPO)}")
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(REPO))
    sys.exit(main())
