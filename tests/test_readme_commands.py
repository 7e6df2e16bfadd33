"""Every command of README.md runs as written, through the real `sefa` command (in-process:
`sefa_cli.main.main` with its argv) on real data (../shared/data, or `sefa collect`'s scripted
demonstrations), and its snippets run on real exports.

`test_every_readme_command_is_run_here` lists each README command with the test that runs it,
so a command added to the README without a test fails. Runs are made small the way the README
says a run is made small (`training.max_steps`, `--max-windows`, `--samples`, `--episodes`,
`--n-test`): the small settings are appended after the README's own, so what is scored is what
the command does, never skill. Two commands are not run here and say why: `make demo` and
`make test` (the test suite itself); the Makefile is checked to run `sefa demo` and pytest. The
README's openpi snippet is not run here: openpi-client pins numpy < 2 and lives in its own venv,
where tests/sefa_deploy_tests/test_serve_openpi.py drives a `sefa serve` process with it.

Regressions kept here: the Push-T walk's `sefa train shape_meta.obs.state.dims=[0,2]
policy.head=mlp` (now in the SeFA stages guide) trains on keypoint and state (it trained on state
alone: naming one key dropped the others); the deployment snippets run against real exports of a
LeRobot store, whose key `observation.state` is the exported input's name too.
"""

from __future__ import annotations

import json
import re
import shlex
import subprocess
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
README = (REPO / "README.md").read_text()
STAGES_GUIDE = (REPO / "docs" / "guides" / "sefa_stages.md").read_text()
# README's training commands with a tiny network and length appended: only what they train on
# is scored here, never skill
TINY = ["policy.mlp_hidden_dims=[32,32]", "policy.time_embed_dim=16", "training.max_steps=4",
        "training.batch_size=16", "training.lr_warmup_steps=1", "training.val_every=4",
        "training.checkpoint_every=4", "training.val_batches=1", "training.val_sample_windows=4",
        "flow.solver=euler", "flow.steps=2", "--threads", "1"]
SMALL_REFLOW = ["--max-windows", "16", "--samples", "2", "--threads", "1"]

# README's commands (the start of each line of its ```bash blocks), by the test that runs them
SETUP = ["make demo", "make test"]
QUICKSTART = ["sefa collect lift.hdf5", "sefa ingest lift.hdf5", "sefa train --preset lift",
              "sefa reflow --max-windows 300", "sefa align --eps auto -w quick",
              "sefa distill -w quick", "sefa eval train distill --offline",
              "sefa eval distill --env robosuite:Lift", "sefa status -w quick"]
OWN_BAG = ["sefa inspect my_run.bag", "sefa ingest my_run.bag --scaffold",
           "sefa ingest my_run.bag --map", "sefa convert my_run.bag"]
OWN_FORMATS = ["sefa ingest demos.hdf5", "sefa ingest replay.zarr", "sefa ingest lerobot_ds/",
               "sefa inspect -w mine"]
SMALL_PIPELINE = ["sefa train --preset lerobot_camera_cpu", "sefa reflow --max-windows 500",
                  "sefa align --eps auto -w mine", "sefa distill -w mine",
                  "sefa eval --offline -w mine"]
DEPLOY = ["sefa export distill --format onnx", "sefa export distill --format torchscript",
          "sefa export train --format onnx", "sefa serve deploy/onnx"]
RUN_BY = {"test_readme_setup_targets": SETUP, "test_readme_quickstart": QUICKSTART,
          "test_readme_own_bag": OWN_BAG, "test_readme_own_formats": OWN_FORMATS,
          "test_readme_small_pipeline": SMALL_PIPELINE, "deployed (fixture)": DEPLOY[:3],
          "test_readme_serve_and_client_snippet": DEPLOY[3:]}


def doc_commands(text: str) -> list[str]:
    """The command lines of a Markdown text's ```bash blocks (continuations joined)."""
    lines = []
    for block in re.findall(r"```bash\n(.*?)```", text, re.S):
        for line in block.replace("\\\n", " ").splitlines():
            if line.strip() and not line.lstrip().startswith("#"):
                lines.append(line.strip())
    return lines


def doc_command(text: str, prefix: str) -> list[str]:
    """The one command line of `text` starting with `prefix`, as argv after `sefa` (its comment
    dropped)."""
    lines = [line for line in text.splitlines() if line.startswith(prefix)]
    assert len(lines) == 1, f"{len(lines)} lines start with {prefix!r}"
    return shlex.split(lines[0], comments=True)[1:]


def readme_command(prefix: str) -> list[str]:
    return doc_command(README, prefix)


def test_every_readme_command_is_run_here():
    prefixes = [p for group in RUN_BY.values() for p in group]
    for line in doc_commands(README):
        owners = [p for p in prefixes if line.startswith(p)]
        assert len(owners) == 1, f"README command not run by a test here: {line!r}"
    for p in prefixes:
        readme_command(p)  # each names exactly one README line


def test_readme_setup_targets():
    """`make demo` is `sefa demo` and `make test` the test suite, each after the venv's setup:
    not run here (the demo takes minutes; `make test` is this suite). `make -n` shows what each
    runs."""
    for target, runs in (("demo", "bin/sefa demo"), ("test", "bin/python -m pytest -q")):
        assert readme_command(f"make {target}") == [target]
        out = subprocess.run(["make", "-n", "-W", "pyproject.toml", target], cwd=REPO,
                             capture_output=True, text=True)
        assert out.returncode == 0, out.stderr
        assert "bash scripts/setup.sh" in out.stdout and runs in out.stdout, out.stdout


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

    from sefa_cli.main import main

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


def refused(argv: list) -> str:
    """`sefa ARGV` in this process, expected to stop with one error line; that line."""
    import contextlib
    import io
    import sys

    from sefa_cli.main import main

    err, saved = io.StringIO(), sys.argv
    sys.argv = ["sefa", *map(str, argv)]
    try:
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err), \
                pytest.raises(SystemExit) as e:
            main()
    finally:
        sys.argv = saved
    lines = [ln for ln in err.getvalue().splitlines() if ln.startswith("error: ")]
    assert e.value.code == 1 and len(lines) == 1, err.getvalue()[-3000:]
    return lines[0]


def aligned_after_refusal(argv: list) -> str:
    """README's `sefa align --eps auto` on these tests' 4-step base flows: it stops, saying the
    flow's samples are farther from the expert than the mean action (the flow is not trained);
    then the eps it named, given as a number, aligns the same nearest 20 % as the README's next
    step would after a longer training."""
    line = refused(argv)
    eps = re.search(r"the nearest 20% of the couplings lie up to (\S+) from the expert's", line)
    assert eps and "the base flow is not trained enough" in line, line
    return sefa([a if a != "auto" else eps.group(1) for a in argv])


def run_readme(prefixes: list[str], small: dict[str, list]) -> dict[str, str]:
    """README's commands in order, each with its small settings appended; its `sefa align --eps
    auto` (after these tests' 4-step flows) refused, then run at the eps it named."""
    return {p: aligned_after_refusal(readme_command(p)) if p.startswith("sefa align --eps auto")
            else sefa(readme_command(p) + small.get(p, [])) for p in prefixes}


def small_pusht(shared_data: Path, folder: Path, episodes: int = 5,
                name: str = "pusht_cchi_v7_replay.zarr") -> Path:
    """The first real Push-T episodes (low-dim keys) under the name the docs' command reads."""
    import zarr

    src = zarr.open_group(str(shared_data / "pusht_cchi_v7_replay.zarr"), mode="r")
    ends = src["meta/episode_ends"][:episodes]
    path = folder / name
    root = zarr.open_group(str(path), mode="w", zarr_format=2)
    for key in ("keypoint", "state", "action"):
        root.create_array(f"data/{key}", data=src["data"][key][: ends[-1]])
    root.create_array("meta/episode_ends", data=ends)
    return path


def test_readme_pusht_training_sees_keypoint_and_state(shared_data, tmp_path, monkeypatch):
    small_pusht(shared_data, tmp_path)
    monkeypatch.chdir(tmp_path)  # README's paths are relative: the recording, then ./
    sefa(doc_command(STAGES_GUIDE, "sefa ingest pusht_cchi_v7_replay.zarr"))
    out = sefa(doc_command(STAGES_GUIDE, "sefa train shape_meta.obs.state.dims") + TINY)

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
    from sefa_cli.main import main

    small_pusht(shared_data, tmp_path, episodes=2)
    monkeypatch.chdir(tmp_path)
    sefa(doc_command(STAGES_GUIDE, "sefa ingest pusht_cchi_v7_replay.zarr"))
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


# --- the quickstart and the pipeline on your own data ---------------------------------------

def test_readme_quickstart(tmp_path, monkeypatch):
    """The quickstart's nine commands in order, in a fresh folder (the preset is named, not a
    path: it works outside a clone): scripted Lift demonstrations
    (`sefa collect`, robosuite) through every stage to a one-step student evaluated offline and
    in the simulator. Small: 3 episodes, a tiny network of 4 steps, 16 windows x 2 noises, one
    episode of 30 steps in the simulator."""
    pytest.importorskip("robosuite", reason="the sim extra is not installed")
    monkeypatch.chdir(tmp_path)
    small = {"sefa collect lift.hdf5": ["--episodes", "3"], "sefa train --preset lift": TINY,
             "sefa reflow --max-windows 300": SMALL_REFLOW,
             "sefa eval distill --env robosuite:Lift": ["--n-test", "1", "--max-steps", "30"]}
    out = run_readme(QUICKSTART, small)

    assert "3/3 successful episodes kept" in out["sefa collect lift.hdf5"]
    assert (tmp_path / "quick" / "dataset.zarr").is_dir()
    status = json.loads(sefa(["status", "-w", "quick", "--json"]))
    state = {r["stage"]: r["state"] for r in status["rows"]}
    assert {k: state[k] for k in ("ingest", "train", "reflow iter 1", "align", "distill")} == {
        "ingest": "done", "train": "cached", "reflow iter 1": "cached", "align": "cached",
        "distill": "cached"}, state
    # the student was SeFA's: alignment replaced the nearest 20 % of its 16 x 2 couplings
    distill = json.loads((tmp_path / "quick/distill/manifest.json").read_text())
    assert distill["summary"]["kind"] == "sefa_one_step", distill["summary"]
    results = json.loads(sefa(["results", "-w", "quick", "--json"]))
    modes = sorted((r["checkpoint"], r["mode"]) for r in results)
    assert modes == [("distill", "offline"), ("distill", "robosuite:Lift"),
                     ("train", "offline")], modes


def test_readme_own_bag(shared_data, tmp_path, monkeypatch):
    """A real ROS 1 bag (the KUKA arm's joint states, ../shared/data) under the README's name:
    inspect it, scaffold its topic map, ingest with that map as written, convert it to a LeRobot
    dataset."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "my_run.bag").symlink_to(shared_data / "kuka_lwr_honeypot_joint_states.bag")
    out = sefa(readme_command(OWN_BAG[0]))
    assert "/joint_states" in out
    sefa(readme_command(OWN_BAG[1]))
    assert "topic: \"/joint_states\"" in (tmp_path / "my_map.yaml").read_text()
    out = sefa(readme_command(OWN_BAG[2]))
    assert "store: mine/dataset.zarr: 1 episodes, 4100 frames appended" in out
    out = sefa(readme_command(OWN_BAG[3]))
    info = json.loads((tmp_path / "my_lerobot/meta/info.json").read_text())
    assert info["codebase_version"] == "v3.0" and info["total_frames"] == 4100


@pytest.mark.parametrize("prefix, source", [
    ("sefa ingest demos.hdf5", "robosuite141_lift_panda_3demos.hdf5"),
    ("sefa ingest replay.zarr", None),  # the first 5 Push-T episodes, low-dim keys
    ("sefa ingest lerobot_ds/", "lerobot_pusht5_image_v30"),
])
def test_readme_own_formats(shared_data, tmp_path, monkeypatch, prefix, source):
    """Each format's ingest line as written, on a real file under the README's name, then
    `sefa inspect -w mine` on the store it made."""
    monkeypatch.chdir(tmp_path)
    name = readme_command(prefix)[1].rstrip("/")
    if source is None:
        small_pusht(shared_data, tmp_path, name=name)
    else:
        (tmp_path / name).symlink_to(shared_data / source)
    sefa(readme_command(prefix))
    out = json.loads(sefa(readme_command("sefa inspect -w mine") + ["--json"]))
    episodes = {"sefa ingest demos.hdf5": 3, "sefa ingest replay.zarr": 5,
                "sefa ingest lerobot_ds/": 5}[prefix]
    assert out["n_episodes"] == episodes, out


def test_readme_small_pipeline(shared_data, tmp_path, monkeypatch):
    """The small pipeline after an ingest (the Push-T Zarr line): train, reflow, align, distill,
    offline evaluation as written, smaller still; then the README's `sefa config set`."""
    monkeypatch.chdir(tmp_path)
    small_pusht(shared_data, tmp_path, name="replay.zarr")
    sefa(readme_command("sefa ingest replay.zarr"))
    small = {"sefa train --preset lerobot_camera_cpu": TINY,
             "sefa reflow --max-windows 500": SMALL_REFLOW}
    out = run_readme(SMALL_PIPELINE, small)
    # the README's knobs are what ran: 16 windows x K = 2, blocks of 64 windows
    assert re.search(r"16 windows of \d+ x K=2 = 32 couplings with rk45, 64 windows per block",
                     out["sefa reflow --max-windows 500"]), out["sefa reflow --max-windows 500"]
    assert "distill" in out["sefa eval --offline -w mine"]
    sefa(["config", "set", "reflow.max_windows", "500", "-w", "mine"])  # README's prose
    shown = json.loads(sefa(["config", "show", "-w", "mine", "--json"]))
    assert shown["sefa.yaml"]["reflow"]["max_windows"] == 500
    assert shown["resolved"]["reflow"]["batch_windows"] == 64  # --block-windows, kept as a flag


def test_readme_small_run_is_cpu_sized_on_a_camera_store(shared_data, tmp_path, monkeypatch):
    """README's small-run `sefa train` on a LeRobot camera store (Push-T's 96x96 camera, 5
    episodes) trains what it says: cameras at 64x64, the tiny encoder, an MLP, batch 32, and
    says its cost before its first step. (It was `sefa train training.max_steps=2000
    policy.head=mlp`, which on a camera store kept the `small` encoder at batch 256: 49 hours
    announced on a 480x640 camera dataset.)"""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "lerobot_ds").symlink_to(shared_data / "lerobot_pusht5_image_v30")
    sefa(readme_command("sefa ingest lerobot_ds/"))
    out = sefa(readme_command("sefa train --preset lerobot_camera_cpu") + [
        "training.max_steps=2", "training.val_every=2", "training.checkpoint_every=2",
        "training.val_batches=1", "training.val_sample_windows=4", "training.lr_warmup_steps=1",
        "flow.solver=euler", "flow.steps=2", "--threads", "1"])
    cfg = json.loads((tmp_path / "mine/train/checkpoints/latest/config.json").read_text())
    p = cfg["train_config"]["policy"]
    assert (p["image_encoder"], p["resize_shape"], p["head"]) == ("tiny", [64, 64], "mlp")
    assert cfg["train_config"]["training"]["batch_size"] == 32
    assert "observation.image (96, 96, 3) rgb resized to 64x64" in out
    assert "cost: 2 steps of batch 32, about" in out


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
        for prefix in DEPLOY[:3]:
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
    from sefa_model.policy.artifact import Policy

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
    exec(readme_python("In Python, a checkpoint is a policy"), scope)
    assert scope["out"].action.shape == (1, 8, 2)


class _OneChunk(Exception):
    """Ends README's endless robot loop after its first chunk."""


class _Robot:
    def __init__(self):
        self.applied = []

    def apply(self, action):
        self.applied.append(np.asarray(action))
        if len(self.applied) == 8:  # the whole first chunk of n_action_steps
            raise _OneChunk


def test_readme_serve_and_client_snippet(deployed):
    """README's `sefa serve deploy/onnx --port 8765` as a process (on a free port instead of
    8765, which a test machine may have in use), driven by README's robot-side snippet as
    written (its URL pointed at that port): its first chunk is the export's own answer."""
    from deploy_helpers import Server
    from sefa_model.policy.artifact import Policy

    ws = deployed
    argv = readme_command(DEPLOY[3])
    assert argv[:2] == ["serve", "deploy/onnx"] and argv[2:] == ["--port", "8765"]
    server = Server(ws / argv[1])
    try:
        robot, history = _Robot(), real_obs(Policy.load(ws / "distill", device="cpu"))
        snippet = readme_python("On the robot's computer").replace("ws://127.0.0.1:8765",
                                                                  server.url)
        with pytest.raises(_OneChunk):
            exec(snippet, {"robot": robot, "history": history})
        assert np.stack(robot.applied).shape == (8, 2)
        assert np.isfinite(np.stack(robot.applied)).all()
    finally:
        code, _, err = server.stop()
    assert code == 0, err[-2000:]


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


def test_an_export_runs_the_execution_given_or_chosen_and_goes_stale_when_another_is_chosen(
        deployed):
    """An export records the execution `sefa serve` runs for it: the one given to `sefa export`
    (kept whatever is chosen later), else the one chosen for the policy; once another is
    chosen, `sefa status` calls an export of the chosen one stale with the command that makes
    it again. Bad execution options are one line each, with nothing written."""
    from sefa_model.policy.checkpoint import EXECUTION_FILE, resolve_checkpoint
    from sefa_model.policy.execution import ExecutionSettings, save_choice

    ws = deployed
    sefa(["export", "distill", "--format", "torchscript", "--out", "deploy/every2",
          "--execution", "receding", "--replan-every", "2"])
    given = json.loads((ws / "deploy/every2/metadata.json").read_text())
    assert given["execution_source"] == "given"
    assert ExecutionSettings.from_json(given["execution"]).label == "receding K=2"
    chosen = json.loads((ws / "deploy/onnx/metadata.json").read_text())
    assert (chosen["execution"], chosen["execution_source"]) == (None, "default")
    for bad, line in ((["--execution", "nonsense"], "--execution: not one of"),
                      (["--replan-every", "99"], "--replan-every: 99 is outside 1..8"),
                      (["--execution", "bid"], "--execution: bid contrasts the policy with a "
                                               "weaker one, which an export does not carry")):
        out = refused(["export", "distill", "--out", "deploy/bad", *bad])
        assert line in out
        assert not (ws / "deploy/bad").exists()

    setting = f"{chosen['solver']}-{chosen['steps']}"

    def export_rows():
        return {r["path"]: r for r in json.loads(sefa(["status", "--json"]))["rows"]
                if r["stage"] == "export"}
    # a choice that keeps the default is what the export runs already
    save_choice(ws / "distill", ExecutionSettings("receding").resolved(8), setting, {})
    try:
        assert export_rows()["deploy/onnx"]["state"] == "done"
        save_choice(ws / "distill", ExecutionSettings("receding", 4).resolved(8), setting, {})
        rows = export_rows()
        assert rows["deploy/every2"]["state"] == "done"
        assert rows["deploy/onnx"]["state"] == rows["deploy/ts"]["state"] == "stale"
        assert rows["deploy/onnx"]["reason"] == (
            "distill has another execution chosen since: receding K=4, where the export runs "
            "receding K=8; export again: sefa export distill --format onnx --out deploy/onnx")
        sefa(["export", "distill", "--format", "onnx", "--out", "deploy/onnx"])
        meta = json.loads((ws / "deploy/onnx/metadata.json").read_text())
        assert (ExecutionSettings.from_json(meta["execution"]).label, meta["execution_source"]) == (
            "receding K=4", "chosen")
        assert export_rows()["deploy/onnx"]["state"] == "done"
    finally:  # the tests after this one serve the policy's default execution
        (resolve_checkpoint(ws / "distill") / EXECUTION_FILE).unlink()


def test_a_preset_that_names_every_observation_key_keeps_its_cache_key(shared_data, tmp_path):
    """Presets made before obs_keys existed name every observation key in `shape_meta.obs`
    (the cpu profile: keypoint and state). Read the new way they mean the same set in the same
    order, so a workspace trained on one is not retrained after the upgrade; a config naming a
    subset (README's old command) or another order means something new and gets a new key."""
    from conftest import pusht_image_store
    from sefa_pipelines.stages import PipelineConfig, base_train_config
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
