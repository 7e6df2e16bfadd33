"""Methods from packages of their own (the `sefa.methods` entry point, docs/extending.md): a
plugin with settings of its own trains through `sefa distill --method` and its checkpoint loads
in a fresh process for `sefa eval`; a broken plugin is named in one warning and left out; an
error inside a plugin's method is reported as the plugin's, in one line.

Each plugin is a real installed distribution as importlib.metadata finds one: a module and a
`*.dist-info` folder (METADATA, entry_points.txt) written into a folder on the child's
PYTHONPATH, which is what `pip install` of a package with that entry point leaves behind. The
commands run as child processes: a plugin must be found by every process, not registered in
the test's."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from deploy_helpers import student_workspace

REPO = Path(__file__).resolve().parents[2]
SEFA = Path(sys.executable).parent / "sefa"

# A student like the reference one with a loss weight of its own: a method in one file, with
# its settings as a Knobs dataclass
KNOBBED = '''
from dataclasses import dataclass

import torch

from sefa_data.ranges import POSITIVE, knob
from sefa_model.flow.rectified_flow import flow_loss
from sefa_model.methods.base import Method, Times


@dataclass
class Knobs:
    weight: float = knob(2.0, POSITIVE)


class Weighted(Method):
    name = "weighted_student"
    label = "one-step (weighted MSE at t = 0)"
    summary = "the reference student, its loss scaled by method_config.weight"
    Knobs = Knobs

    def draw(self, cfg, n, gen):
        return Times(torch.zeros(n))

    def loss(self, cfg, calls, x0, x1, times, gen=None):
        return self.knobs(cfg).weight * flow_loss(lambda x, t: calls.f(x, t), x0, x1, times.t)

    def time_words(self, flow):
        return "0 (one step), weighted"


METHOD = Weighted()
'''


def plugin(root: Path, module: str, source: str, entry: str) -> Path:
    """A distribution `module` in `root`: its module and its dist-info, one entry point."""
    root.mkdir(parents=True, exist_ok=True)
    (root / f"{module}.py").write_text(textwrap.dedent(source))
    info = root / f"{module}-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {module}\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(f"[sefa.methods]\n{entry} = {module}:METHOD\n")
    return root


def sefa(*args, path: Path, cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(path), *filter(None, [os.environ.get("PYTHONPATH")])])}
    return subprocess.run([str(SEFA), *map(str, args)], capture_output=True, text=True, cwd=cwd,
                          env=env, timeout=600)


@pytest.fixture()
def workspace(deploy_workspace, tmp_path):
    """A workspace on the deployment tests' tiny store, its student `distill_method`."""
    def make(distill_method: str, extra: str = "") -> Path:
        return student_workspace(deploy_workspace, tmp_path / "ws", distill_method, extra)
    return make


def test_a_plugin_method_with_settings_trains_and_loads_in_a_fresh_process(workspace, tmp_path):
    path = plugin(tmp_path / "site", "sefa_weighted_student", KNOBBED, "weighted_student")
    ws = workspace("weighted_student", ", 'method_config.weight=3'")
    r = sefa("distill", "--yes", "-w", ws, path=path, cwd=ws)
    assert r.returncode == 0, r.stderr[-2000:]
    ckpt = ws / "distill" / "checkpoints" / "latest"
    config = json.loads((ckpt / "config.json").read_text())["train_config"]
    # the settings are recorded resolved, as the method's own, and so in the cache key
    assert config["method"] == "weighted_student" and config["method_config"] == {"weight": 3.0}
    manifest = json.loads((ws / "distill" / "manifest.json").read_text())
    assert '"weight": 3.0' in json.dumps(manifest)
    r = sefa("eval", "distill", "--offline", "--windows", "8", "--json", "-w", ws, path=path, cwd=ws)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "weighted_student" not in r.stderr  # no warning about the plugin
    # without the plugin installed, the method it needs is named, in one line
    r = sefa("eval", "distill", "--offline", "--windows", "8", "-w", ws, path=tmp_path / "none", cwd=ws)
    lines = [line for line in r.stderr.splitlines() if line.strip()]
    assert r.returncode != 0 and len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    assert "unknown method 'weighted_student' (students, nearest first: " in lines[0], lines


def test_a_setting_the_method_does_not_have_is_one_line(workspace, tmp_path):
    path = plugin(tmp_path / "site", "sefa_weighted_student", KNOBBED, "weighted_student")
    ws = workspace("weighted_student", ", 'method_config.wieght=3'")
    r = sefa("distill", "--yes", "-w", ws, path=path, cwd=ws)
    lines = [line for line in r.stderr.splitlines() if line.strip()]
    assert r.returncode != 0 and "Traceback" not in r.stderr, r.stderr
    assert "unknown key 'wieght'; did you mean 'weight'?" in lines[-1], lines


def test_a_plugin_that_fails_to_import_is_left_out_with_one_warning(workspace, tmp_path):
    path = plugin(tmp_path / "site", "sefa_broken_plugin",
                  "import not_a_module_anywhere\nMETHOD = None\n", "broken")
    ws = workspace("reference")
    r = sefa("distill", "--yes", "-w", ws, path=path, cwd=ws)
    assert r.returncode == 0, r.stderr[-2000:]  # the built-in student trains as before
    warned = [line for line in r.stderr.splitlines() if "method plugin broken" in line]
    assert len(warned) == 1, r.stderr
    assert "sefa_broken_plugin:METHOD" in warned[0] and "ModuleNotFoundError" in warned[0]
    r = sefa("eval", "distill", "--offline", "--windows", "8", "-w", ws, path=path, cwd=ws)
    assert r.returncode == 0, r.stderr[-2000:]


def test_an_error_inside_a_plugins_method_is_the_plugins_in_one_line(workspace, tmp_path):
    faulty = KNOBBED.replace('name = "weighted_student"', 'name = "faulty"').replace(
        "return Times(torch.zeros(n))", 'raise RuntimeError("boom in draw")')
    path = plugin(tmp_path / "site", "sefa_faulty_plugin", faulty, "faulty")
    ws = workspace("faulty")
    r = sefa("distill", "--yes", "-w", ws, path=path, cwd=ws)
    lines = [line for line in r.stderr.splitlines() if line.startswith("error")]
    assert r.returncode != 0 and "Traceback" not in r.stderr, r.stderr[-2000:]
    assert "a bug in sefa" not in r.stderr, r.stderr[-2000:]
    assert len(lines) == 1, r.stderr[-2000:]
    assert ("method 'faulty' from the plugin 'sefa_faulty_plugin:METHOD' (package "
            "sefa_faulty_plugin) failed in draw: RuntimeError: boom in draw") in lines[0]
