"""An export is served only as it was written (sefa_deploy/metadata.py:open_export,
sefa_deploy/backends.py:probe): an edited metadata.json or a swapped artifact is refused at load
in one line naming the file, never served to answer every request with an error about shapes.

The exports are the deployment tests' own (tests/deploy_helpers.py: a tiny one-step student on
the real Push-T low-dim data, exported with `export_policy`); each case copies one and edits it
with json, as a user editing the file would.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from deploy_helpers import REPO
from sefa_data.errors import SefaInputError
from sefa_deploy.backends import load_backend


@pytest.fixture(params=["torchscript", "onnx"])
def export(deploy_exports, request, tmp_path) -> Path:
    out = tmp_path / "export"
    shutil.copytree(deploy_exports("one-step", request.param), out)
    return out


def edit(export: Path, change) -> None:
    path = export / "metadata.json"
    meta = json.loads(path.read_text())
    change(meta)
    path.write_text(json.dumps(meta, indent=2))


def _steps(n: int):
    def change(meta: dict) -> None:
        meta["n_action_steps"] = n
    return change


def _consistently(meta: dict) -> None:
    """n_action_steps 16 with every field derived from it edited alike: only running the
    artifact tells (it predicts 8)."""
    meta["n_action_steps"] = 16
    meta["outputs"]["action"]["shape"][0] = 16
    meta["execute"]["stop"] = meta["execute"]["start"] + 16


def test_an_unedited_export_loads_with_and_without_its_checksums(export) -> None:
    assert json.loads((export / "checksums.json").read_text()).keys() == {
        "metadata.json", json.loads((export / "metadata.json").read_text())["file"]}
    load_backend(export)
    (export / "checksums.json").unlink()  # as an export written before checksums
    load_backend(export)


def test_n_action_steps_edited_is_refused_at_load_in_one_line(export) -> None:
    """The issue's case, through `sefa serve`: it started and answered every request with an
    error about shapes."""
    edit(export, _steps(16))
    # a server that starts never exits by itself: the timeout fails the test
    r = subprocess.run([sys.executable, "-m", "sefa_cli.main", "serve", str(export), "--port",
                        "0"], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert r.returncode == 1 and r.stdout == ""
    assert r.stderr.strip().splitlines() == [
        f"error: {export}/metadata.json: checksum mismatch (the file changed after it was "
        "written): the export is damaged"]


@pytest.mark.parametrize("change,said", [
    (_steps(16), "n_action_steps 16 and action_dim 2 make outputs.action.shape [16, 2], but it "
                 "is [8, 2]: the file was edited after the export"),
    (_consistently, "answers action of shape (8, 2), metadata.json says (16, 2): the two are not "
                    "from one export; export again"),
], ids=["n_action_steps", "every-derived-field"])
def test_an_edited_export_without_checksums_is_refused_by_its_own_shapes(export, change,
                                                                         said) -> None:
    (export / "checksums.json").unlink()  # an export written before checksums, edited since
    edit(export, change)
    with pytest.raises(SefaInputError) as e:
        load_backend(export)
    assert e.value.file == str(export / "metadata.json")
    assert said in e.value.line()


def test_an_artifact_swapped_for_another_exports_is_refused(export, deploy_exports) -> None:
    meta = json.loads((export / "metadata.json").read_text())
    other = deploy_exports("euler-4", meta["format"]) / meta["file"]
    shutil.copyfile(other, export / meta["file"])
    with pytest.raises(SefaInputError, match="checksum mismatch .* the export is damaged"):
        load_backend(export)
