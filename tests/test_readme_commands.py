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


def sefa(argv: list) -> str:
    """`sefa ARGV` in this process (cwd: the caller's); its stdout + stderr. Fails the test on
    a non-zero exit."""
    import contextlib
    import io
    import sys

    from cli.main import main

    out, err, saved = io.StringIO(), io.StringIO(), sys.argv
    sys.argv = ["sefa", *map(str, argv)]
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err), \
                pytest.raises(SystemExit) as e:
            main()
    finally:
        sys.argv = saved
    assert e.value.code in (0, None), err.getvalue()[-3000:]
    return out.getvalue() + err.getvalue()


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


def test_readme_pusht_training_sees_keypoint_and_state(shared_data, tmp_path, monkeypatch):
    small_pusht(shared_data, tmp_path)
    monkeypatch.chdir(tmp_path)  # README's paths are relative: the recording, then ./
    sefa(readme_command("sefa ingest pusht_cchi_v7_replay.zarr"))
    out = sefa(readme_command("sefa train shape_meta.obs.state.dims") + TINY)

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
                "policy.head=mlp", *TINY])
    assert "observations (1): state (5,)[0:2]" in out
    assert "not observed: keypoint (left out by shape_meta.obs_keys)" in out
    config = json.loads((tmp_path / "train/checkpoints/latest/config.json").read_text())
    assert list(config["train_config"]["shape_meta"]["obs"]) == ["state"]


def test_a_configured_key_outside_obs_keys_is_one_line(shared_data, tmp_path, monkeypatch,
                                                       capsys):
    from cli.main import main

    small_pusht(shared_data, tmp_path, episodes=2)
    monkeypatch.chdir(tmp_path)
    sefa(readme_command("sefa ingest pusht_cchi_v7_replay.zarr"))
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


# --- deployment (trap 8): README's export commands and snippets on a LeRobot store -------------

@pytest.fixture(scope="module")
def deployed(shared_data, tmp_path_factory):
    """A workspace on a LeRobot store (key `observation.state`) with a tiny base flow and
    one-step policy, exported by README's own `sefa export` commands, run in the workspace."""
    ws = tmp_path_factory.mktemp("lerobot_ws")
    mp = pytest.MonkeyPatch()
    mp.chdir(ws)
    try:
        sefa(["ingest", shared_data / "lerobot_pusht5_image_v30", "--key", "observation.state",
              "--key", "action"])
        sefa(["train", "policy.head=mlp", *TINY])
        sefa(["reflow", "--iters", "1", "--max-windows", "16", "--samples", "2", "--threads", "1"])
        sefa(["distill", "--no-align", "--threads", "1"])
        for prefix in ("sefa export distill --format onnx", "sefa export distill --format torch",
                       "sefa export train --format onnx"):
            sefa(readme_command(prefix))
        yield ws
    finally:
        mp.undo()


def real_obs(policy) -> dict[str, np.ndarray]:
    """The first n_obs_steps frames of the store's first episode, per observation key."""
    from sefa_data.store.zarr_store import EpisodeStore

    episode = EpisodeStore.open(Path("dataset.zarr")).get_episode(0)
    return {k: np.asarray(episode[k][: policy.cfg.policy.n_obs_steps], dtype=np.float32)
            for k in policy.cfg.shape_meta.obs}


def test_readme_deploy_snippets_run_as_written_on_store_keys(deployed):
    import torch

    from sefa_deploy.export import ARTIFACT_ATOL  # the bound export itself checks, action units
    from sefa_model.policy import Policy

    ws = deployed
    meta = json.loads((ws / "deploy/onnx/metadata.json").read_text())
    assert meta["inputs"] == ["observation.state", "noise"]
    assert json.loads((ws / "deploy/ts/metadata.json").read_text())["inputs"] == meta["inputs"]
    policy = Policy.load("distill", device="cpu")
    obs = real_obs(policy)
    assert list(obs) == ["observation.state"]

    onnx_part, ts_part = readme_python("Without a server").split("# TorchScript")
    scope = {"obs": obs}
    exec(onnx_part, scope)  # README's ONNX lines as written, in the workspace
    noise = torch.from_numpy(scope["noise"])
    want = policy.predict_action(obs, noise=noise).action_pred.numpy()
    assert scope["chunk"].shape == want.shape == (1, 16, 2)
    assert np.abs(scope["chunk"] - want).max() <= ARTIFACT_ATOL
    assert np.array_equal(scope["action"], scope["chunk"][:, 1:9])
    exec("# TorchScript" + ts_part, scope)  # ... then its TorchScript lines
    assert np.abs(scope["chunk"].numpy() - want).max() <= ARTIFACT_ATOL

    # README's Python snippet (Policy.load in a workspace) on the same observation
    scope = {"obs": obs}
    exec(readme_python("### The diffusion baseline"), scope)
    assert scope["out"].action.shape == (1, 8, 2)


def test_exports_record_their_checkpoint_and_status_shows_a_stale_one(deployed):
    import hashlib

    ws = deployed
    meta = json.loads((ws / "deploy/euler4/metadata.json").read_text())
    # the checkpoint's identity: the digest of its checksums.json (every file's size and hash)
    sums = (ws / "train/checkpoints/latest/checksums.json").read_bytes()
    assert meta["checkpoint_digest"] == hashlib.sha256(sums).hexdigest()
    assert Path(meta["checkpoint_resolved"]) == (ws / "train/checkpoints/latest").resolve()
    rows = {r["path"]: r for r in json.loads(sefa(["status", "--json"]))["rows"]
            if r["stage"] == "export"}
    assert {p: r["state"] for p, r in rows.items()} == {
        "deploy/onnx": "done", "deploy/ts": "done", "deploy/euler4": "done"}
    old_run = (ws / "train").resolve().name
    assert rows["deploy/euler4"]["metric"] == f"onnx of train (runs/train/{old_run})"

    sefa(["train", "policy.head=mlp", "training.seed=1", *TINY])  # train/ moves to another run
    view = json.loads(sefa(["status", "--json"]))
    rows = {r["path"]: r for r in view["rows"] if r["stage"] == "export"}
    new_run = (ws / "train").resolve().name
    assert new_run != old_run
    assert rows["deploy/euler4"]["state"] == "stale"
    assert rows["deploy/euler4"]["reason"] == (
        f"train was made again since: now runs/train/{new_run}; export again: sefa export train "
        f"--format onnx --solver euler --steps 4 --out deploy/euler4")
    # the one-step policy's pointer has not moved (distill is stale, not yet made again)
    assert rows["deploy/onnx"]["state"] == rows["deploy/ts"]["state"] == "done"


def test_a_preset_that_names_every_observation_key_keeps_its_cache_key(shared_data, tmp_path):
    """Presets made before obs_keys existed name every observation key in `shape_meta.obs`
    (the cpu profile: keypoint and state). Read the new way they mean the same set in the same
    order, so a workspace trained on one is not retrained after the upgrade; a config naming a
    subset (README's old command) or another order means something new and gets a new key."""
    from conftest import pusht_image_store
    from pipelines.stages import PipelineConfig, base_train_config
    from sefa_model.config import cache_key_dict

    store = pusht_image_store(shared_data, tmp_path)  # observation keys: img, state
    ws = tmp_path / "ws"
    ws.mkdir()
    (ws / "dataset.zarr").symlink_to(store)

    def key(*overrides):
        return cache_key_dict(base_train_config(ws, PipelineConfig(train=list(overrides))))

    both = key("shape_meta.obs.img.type=rgb", "shape_meta.obs.state.type=low_dim")
    assert "obs_keys" not in both["shape_meta"]  # the key it had before issue 25
    assert key("shape_meta.obs.state.dims=[0,2]")["shape_meta"]["obs_keys"] == "every store key"
    reordered = key("shape_meta.obs.state.type=low_dim", "shape_meta.obs.img.type=rgb")
    assert reordered["shape_meta"]["obs_keys"] == "every store key"
