"""What `pip install sefa` puts into site-packages: every import name starts with sefa_ (the
folders cli/ and pipelines/ install as sefa_cli and sefa_pipelines: pyproject.toml says why), every
package folder is in the wheel, the presets travel with sefa_pipelines, and no source imports the
two folders by their own names (which would load their modules a second time)."""

from __future__ import annotations

import ast
import re
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
FOLDERS = {"sefa_data": "sefa_data", "sefa_model": "sefa_model", "sefa_sim": "sefa_sim",
           "sefa_deploy": "sefa_deploy", "pipelines": "sefa_pipelines", "cli": "sefa_cli"}


def declared() -> dict:
    return tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]


def test_the_package_list_is_every_package_folder_under_its_installed_name():
    found = set()
    for folder, name in FOLDERS.items():
        for init in (REPO / folder).rglob("__init__.py"):
            rel = init.parent.relative_to(REPO / folder).parts
            found.add(".".join((name, *rel)))
    assert set(declared()["packages"]) == found
    assert declared()["package-dir"] == {"sefa_cli": "cli", "sefa_pipelines": "pipelines"}


def test_the_wheel_installs_only_sefa_names_with_the_presets(tmp_path):
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q",
                    "-w", str(tmp_path), str(REPO)], check=True, capture_output=True, timeout=300)
    (wheel,) = tmp_path.glob("sefa-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    top = {n.split("/")[0] for n in names if not n.split("/")[0].endswith(".dist-info")}
    assert top == set(FOLDERS.values())
    presets = {Path(n).name for n in names if n.startswith("sefa_pipelines/") and n.endswith(".yaml")}
    assert presets == {p.name for p in (REPO / "pipelines").glob("*.yaml")}
    scripts = next(n for n in names if n.endswith("entry_points.txt"))
    assert "sefa = sefa_cli.main:main" in zipfile.ZipFile(wheel).read(scripts).decode()


OLD = re.compile(r"^(cli|pipelines)(\.|$)")


def old_imports(path: Path) -> list[str]:
    """Imports and `-m` module strings that name cli or pipelines by the folder's name."""
    tree = ast.parse(path.read_text(), str(path))
    bad = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            bad += [a.name for a in node.names if OLD.match(a.name)]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and OLD.match(node.module or ""):
            bad.append(node.module)
        elif isinstance(node, ast.Constant) and isinstance(node.value, str) and OLD.match(node.value) \
                and re.fullmatch(r"[a-z_.]+", node.value) and "." in node.value:
            bad.append(node.value)  # "cli.main" for `python -m`, monkeypatch targets
    return bad


@pytest.mark.parametrize("where", ["sefa_data", "sefa_model", "sefa_sim", "sefa_deploy", "pipelines",
                                   "cli", "tests", "benchmarks", "scripts"])
def test_no_source_imports_cli_or_pipelines_by_the_folder_name(where):
    found = {str(p.relative_to(REPO)): b for p in (REPO / where).rglob("*.py")
             if (b := old_imports(p))}
    assert not found


def test_the_folder_name_warns_the_installed_name_does_not():
    code = ("import warnings, importlib; warnings.simplefilter('error');"
            "importlib.import_module('sefa_cli'); importlib.import_module('sefa_pipelines');"
            "\ntry:\n importlib.import_module('cli')\nexcept DeprecationWarning as e:\n print(e)")
    done = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "'cli' is the folder's name; import sefa_cli"
