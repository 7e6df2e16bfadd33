"""The documentation site: its reference pages list every command and every setting the code
has (they are generated from it, scripts/gen_reference.py), the site builds with MkDocs with
warnings as errors (broken links and anchors included), and the user docs speak to users (no
issue numbers, no remarks about the machine they were written on)."""

from __future__ import annotations

import dataclasses
import importlib
import importlib.util
import re
import subprocess
import sys
import typing
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def _script(name: str):
    """A module of scripts/ (not a package), loaded without putting scripts/ on sys.path."""
    spec = importlib.util.spec_from_file_location(name, REPO / "scripts" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


gen_reference = _script("gen_reference")


def sections(page: str) -> dict[str, str]:
    """`## TITLE` -> the text under it."""
    parts = re.split(r"^## (.+)$", page, flags=re.M)
    return {parts[i].strip(): parts[i + 1] for i in range(1, len(parts), 2)}


def every_command() -> dict[str, object]:
    """'sefa ingest', 'sefa bench data', ... -> its click command, read from the root app by
    walking typer's click group here (not with the generator's own walk)."""
    import typer

    from sefa_cli.main import app

    out = {}

    def walk(group, path):
        ctx = group.context_class(group, info_name=path)
        for name in group.list_commands(ctx):
            cmd = group.get_command(ctx, name)
            if hasattr(cmd, "list_commands"):
                walk(cmd, f"{path} {name}")
            else:
                out[f"{path} {name}"] = cmd

    walk(typer.main.get_command(app), "sefa")
    return out


def test_the_command_reference_has_every_command_and_option():
    page = sections(gen_reference.commands_page())
    commands = every_command()
    # the CLI's commands as of this writing are all there (a guard against an empty walk)
    assert {"sefa ingest", "sefa train", "sefa reflow", "sefa align", "sefa distill", "sefa run",
            "sefa eval", "sefa export", "sefa serve", "sefa convert", "sefa bench latency",
            "sefa config set"} <= set(commands)
    assert set(page) == set(commands)
    for name, cmd in commands.items():
        text = page[name]
        for p in cmd.params:
            if getattr(p, "param_type_name", "") == "argument":
                assert f"`{p.name.upper()}`" in text, (name, p.name)
            else:
                for opt in [*p.opts, *p.secondary_opts]:
                    assert f"`{opt}`" in text, (name, opt)
    # defaults and help as the code states them
    reflow = page["sefa reflow"]
    assert re.search(r"\| `--block-windows` \| integer \|  \| Windows per solved block", reflow)
    assert "| `--zarr-format` | integer | 2 | Zarr format of a new store (2 or 3). |" in \
        page["sefa ingest"]


def field_keys(cls, prefix: str = "") -> list[str]:
    """Every settable key of a settings dataclass, dotted; a per-key map's fields under KEY."""
    hints = typing.get_type_hints(cls)
    keys = []
    for f in dataclasses.fields(cls):
        hint = hints[f.name]
        args = typing.get_args(hint)
        if typing.get_origin(hint) is dict and len(args) == 2 and dataclasses.is_dataclass(args[1]):
            keys.append(prefix + f.name)
            keys += field_keys(args[1], f"{prefix}{f.name}.KEY.")
        elif dataclasses.is_dataclass(hint):
            keys += field_keys(hint, f"{prefix}{f.name}.")
        elif len(args) == 2 and type(None) in args and any(map(dataclasses.is_dataclass, args)):
            inner = next(a for a in args if dataclasses.is_dataclass(a))  # an optional section
            keys += field_keys(inner, f"{prefix}{f.name}.")
        else:
            keys.append(prefix + f.name)
    return keys


def test_the_settings_reference_has_every_field_with_its_default_and_range():
    page = gen_reference.settings_page()
    by_title = sections(page)
    roots = {title: getattr(importlib.import_module(module), name)
             for title, module, name, _ in gen_reference.SETTINGS}
    # the four settings files a user writes
    assert [r.__name__ for r in roots.values()] == ["TrainConfig", "PipelineConfig", "TopicMap",
                                                    "Hdf5Options"]
    for title, root in roots.items():
        keys = field_keys(root)
        rows = re.findall(r"^\| `([^`]+)` \|", by_title[title], flags=re.M)
        assert rows == keys, title
    train, pipeline = by_title["Train config"], by_title["Workspace settings (sefa.yaml)"]
    assert "| `training.max_steps` | `int` | `5000` | an integer in [1, 100000000] |" in train
    assert "| `policy.image_encoder` | one of `tiny`, `small`, `resnet18` | `small` |" in train
    assert "| `reflow.batch_windows` | `int` | `256` | an integer in [1, 1000000] |" in pipeline
    # the comment beside a field is its help
    assert "the cosine decay's length; None: max_steps." in train


def _knob(default):
    from sefa_data.ranges import count, knob

    return knob(default, count(1, 9))


@dataclasses.dataclass
class _Section:
    count: int = _knob(3)  # how many of them


@dataclasses.dataclass
class _Root:
    name: str = "x"
    section: _Section = dataclasses.field(default_factory=_Section)


def test_a_new_field_is_in_the_reference_without_editing_it():
    """The page is the code's: a field added to a settings dataclass appears at once, with its
    default, range and comment."""
    rows = list(gen_reference.setting_rows(_Root))
    assert [r[0] for r in rows] == ["name", "section.count"]
    assert rows[1][2:] == ("`3`", "an integer in [1, 9]", "how many of them")


def test_the_written_pages_are_the_code_s(tmp_path):
    written = gen_reference.write(tmp_path)
    assert sorted(p.name for p in written) == ["commands.md", "settings.md"]
    assert gen_reference.write(tmp_path) == []  # unchanged pages are left as they are


def test_the_committed_reference_pages_are_the_code_s():
    """docs/reference/ is committed, so that the guides' links to it work in a clone and on
    GitHub (they were dead until `make docs` wrote the pages); `--check` finds them current.
    A change to a command's help or a setting fails here until `python
    scripts/gen_reference.py` writes the pages again."""
    run = [sys.executable, str(REPO / "scripts" / "gen_reference.py"), "--check"]
    r = subprocess.run(run, cwd=REPO, capture_output=True, text=True)
    assert r.returncode == 0 and r.stderr.count("out of date") == 0, r.stderr[-2000:]
    assert "## sefa ingest" in (REPO / "docs/reference/commands.md").read_text()
    tracked = subprocess.run(["git", "ls-files", "docs/reference"], cwd=REPO,
                             capture_output=True, text=True)
    if tracked.returncode == 0:  # a git checkout (not an unpacked sdist)
        assert tracked.stdout.split() == ["docs/reference/commands.md",
                                          "docs/reference/settings.md"]


def test_every_settings_file_a_commands_help_names_is_shipped():
    """`sefa run --help` cited pipelines/pusht_small.yaml, which no checkout has: every
    pipelines/NAME.yaml that any command's help names is a file of the package."""
    named = set(re.findall(r"pipelines/([\w.-]+\.yaml)", gen_reference.commands_page()))
    missing = sorted(n for n in named if not (REPO / "pipelines" / n).is_file())
    assert not missing, missing


def test_every_relative_link_of_the_docs_names_a_file_that_is_there():
    """A link from README.md or a page under docs/ to another file resolves in a clone, as
    GitHub renders it (the site's build checks the same for its pages, after generating)."""
    missing = []
    for page in USER_DOCS:
        for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", page.read_text()):
            if "://" in target or target.startswith("mailto:"):
                continue
            if not (page.parent / target).exists():
                missing.append(f"{page.relative_to(REPO)}: {target}")
    assert not missing, "\n".join(missing)


def test_the_site_builds_with_warnings_as_errors(tmp_path):
    pytest.importorskip("mkdocs", reason="the docs extra is not installed (pip install -e .[docs])")
    pytest.importorskip("material", reason="the docs extra is not installed (pip install -e .[docs])")
    r = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir",
                        str(tmp_path / "site")], cwd=REPO, capture_output=True, text=True,
                       env={**__import__("os").environ, "NO_MKDOCS_2_WARNING": "1"})
    assert r.returncode == 0, r.stderr[-3000:]
    html = (tmp_path / "site" / "reference" / "settings" / "index.html").read_text()
    assert "training.max_steps" in html and "reflow.batch_windows" in html
    assert (tmp_path / "site" / "guides" / "ingest" / "index.html").exists()


USER_DOCS = [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md"))]
# what a user's page must not say: an issue number, or a remark about where it was written
NOT_FOR_USERS = re.compile(r"\bissues? \d|\(issue|this (machine|VM)\b|development VM", re.I)


def _user_pages() -> list[tuple[str, str]]:
    """(name, text) of the user docs, and of the generated reference pages as the code writes
    them (their text is the code's help and comments)."""
    pages = [(str(p.relative_to(REPO)), p.read_text()) for p in USER_DOCS
             if p.parent.name != "reference"]
    return pages + [(f"docs/reference/{name}", text)
                    for name, text in gen_reference.pages().items()]


@pytest.mark.parametrize("name, text", _user_pages(), ids=lambda v: v if v.endswith(".md") else "")
def test_user_docs_have_no_issue_numbers_or_machine_remarks(name, text):
    # code spans are left out: they quote the program's own output ("more than this machine's
    # 23.5 GB of memory" is what sefa says to its user)
    bad = [f"{name}:{i}: {line.strip()}" for i, line in enumerate(text.splitlines(), 1)
           if NOT_FOR_USERS.search(re.sub(r"`[^`]*`", "", line))]
    assert not bad, "\n".join(bad)


def test_the_readme_is_a_guide_not_a_notebook():
    lines = (REPO / "README.md").read_text().splitlines()
    assert len(lines) <= 300


def test_the_readme_s_links_resolve():
    """MkDocs checks the site's links; the README is outside the site, so its relative links
    are checked here."""
    text = (REPO / "README.md").read_text()
    links = re.findall(r"\]\(([^)#]+)(?:#[^)]*)?\)", text)
    assert links
    missing = [link for link in links if "://" not in link and not (REPO / link).exists()]
    assert not missing, missing
