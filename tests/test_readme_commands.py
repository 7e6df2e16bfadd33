"""README's commands and snippets do what they say (issue 25, traps 1 and 8), run as written
through the real `sefa` command (in-process: `cli.main.main` with its argv) on small real data:

- the Push-T walk's `sefa train shape_meta.obs.state.dims=[0,2] policy.head=mlp` trains on
  keypoint and state (it trained on state alone: naming one key dropped the others);
- the deployment snippets run against real exports of a LeRobot store, whose key
  `observation.state` is the exported input's name too (it was `observation_state`).
"""

from __future__ import annotations

import json
import re
import shlex
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
README = (REPO / "README.md").read_text()
# README's training commands with a tiny network and length appended: only what they train on
# is scored here, never skill
TINY = ["policy.mlp_hidden_dims=[32,32]", "policy.time_embed_dim=16", "training.max_steps=4",
        "training.batch_size=16", "training.lr_warmup_steps=1", "training.val_every=4",
        "training.checkpoint_every=4", "training.val_batches=1", "training.val_sample_windows=4",
        "flow.solver=euler", "flow.steps=2", "--threads", "1"]


def readme_command(prefix: str) -> list[str]:
    """The one README line starting with `prefix`, as argv after `sefa` (comment dropped)."""
    lines = [line for line in README.splitlines() if line.startswith(prefix)]
    assert len(lines) == 1, f"README has {len(lines)} lines starting with {prefix!r}"
    return shlex.split(lines[0], comments=True)[1:]


def readme_python(after: str) -> str:
    """The first ```python block of README after the text `after`."""
    start = README.index(after)
    block = re.search(r"```python\n(.*?)```", README[start:], re.S)
    return block.group(1)


def sefa(argv: list[str], monkeypatch, capsys) -> str:
    """`sefa ARGV` in this process; its stdout + stderr. Fails the test on a non-zero exit."""
    from cli.main import main

    monkeypatch.setattr("sys.argv", ["sefa", *map(str, argv)])
    with pytest.raises(SystemExit) as e:
        main()
    out = capsys.readouterr()
    assert e.value.code in (0, None), out.err[-3000:]
    return out.out + out.err


def small_pusht(shared_data: Path, folder: Path, episodes: int = 5) -> Path:
    """The first real Push-T episodes (low-dim keys) under the name README's command reads."""
    import zarr

    src = zarr.open_group(str(shared_data / "pusht_cchi_v7_replay.zarr"), mode="r")
    ends = src["meta/episode_ends"][:episodes]
    path = folder / "pusht_cchi_v7_replay.zarr"
    root = zarr.open_group(str(path), mode="w", zarr_format=2)
    for key in ("keypoint", "state", "action"):
        root.create_array(f"data/{key}", data=src["data"][key][: ends[-1]])
    root.create_array("meta/episode_ends", data=ends)
    return path


def test_readme_pusht_training_sees_keypoint_and_state(shared_data, tmp_path, monkeypatch, capsys):
    small_pusht(shared_data, tmp_path)
    monkeypatch.chdir(tmp_path)  # README's paths are relative: the recording, then ./
    sefa(readme_command("sefa ingest pusht_cchi_v7_replay.zarr"), monkeypatch, capsys)
    out = sefa(readme_command("sefa train shape_meta.obs.state.dims") + TINY, monkeypatch, capsys)

    # said when training starts: every key with one frame's shape and the slice read from it
    assert "observations (2): keypoint (9, 2), state (5,)[0:2]" in out, out
    assert "not observed" not in out
    # recorded: the checkpoint's resolved config and the run's manifest
    config = json.loads((tmp_path / "train/checkpoints/latest/config.json").read_text())
    meta = config["train_config"]["shape_meta"]
    assert list(meta["obs"]) == meta["obs_keys"] == ["keypoint", "state"]
    assert meta["obs"]["state"]["dims"] == [0, 2] and meta["obs"]["state"]["shape"] == [2]
    assert meta["obs"]["keypoint"]["dims"] is None and meta["obs"]["keypoint"]["shape"] == [18]
    manifest = json.loads((tmp_path / "train/manifest.json").read_text())
    assert manifest["summary"]["observations"] == {
        "keypoint": {"type": "low_dim", "frame_shape": [9, 2], "dims": None, "shape": [18]},
        "state": {"type": "low_dim", "frame_shape": [5], "dims": [0, 2], "shape": [2]}}

    # the set is chosen with shape_meta.obs_keys, and what it leaves out is said
    out = sefa(["train", "shape_meta.obs_keys=[state]", "shape_meta.obs.state.dims=[0,2]",
                "policy.head=mlp", *TINY], monkeypatch, capsys)
    assert "observations (1): state (5,)[0:2]" in out
    assert "not observed: keypoint (left out by shape_meta.obs_keys)" in out
    config = json.loads((tmp_path / "train/checkpoints/latest/config.json").read_text())
    assert list(config["train_config"]["shape_meta"]["obs"]) == ["state"]


def test_a_configured_key_outside_obs_keys_is_one_line(shared_data, tmp_path, monkeypatch,
                                                       capsys):
    from cli.main import main

    small_pusht(shared_data, tmp_path, episodes=2)
    monkeypatch.chdir(tmp_path)
    sefa(readme_command("sefa ingest pusht_cchi_v7_replay.zarr"), monkeypatch, capsys)
    monkeypatch.setattr("sys.argv", ["sefa", "train", "shape_meta.obs_keys=[keypoint]",
                                     "shape_meta.obs.state.dims=[0,2]", *TINY])
    with pytest.raises(SystemExit) as e:
        main()
    err = capsys.readouterr().err
    errors = [line for line in err.splitlines() if line.startswith("error:")]
    assert e.value.code == 1 and "Traceback" not in err and len(errors) == 1, err
    assert errors[0].startswith("error: shape_meta.obs.state: ")
    assert "not in shape_meta.obs_keys (keypoint)" in errors[0]
    assert not (tmp_path / "train").exists()
