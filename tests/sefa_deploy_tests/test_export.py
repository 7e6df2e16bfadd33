"""`sefa export` (issue 13): ONNX and TorchScript artifacts of a one-step policy and of an
Euler-N flow, checked against `Policy.predict_action` with the same noise on 100 real
validation windows of Push-T; the TorchScript and ONNX files run with sefa blocked from import;
an image policy; the metadata; bad requests for an export."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch

from deploy_helpers import EXPORT_SETTINGS, need, normalize_action, sefa, validation_windows
from sefa_data.errors import SefaInputError
from sefa_deploy.export import export_policy
from sefa_deploy.metadata import load_metadata
from sefa_model.policy.artifact import Policy

TOLERANCE = 1e-4  # normalized action units
SETTINGS = EXPORT_SETTINGS


@pytest.fixture(scope="module")
def ws(deploy_workspace) -> Path:
    return deploy_workspace


@pytest.fixture(scope="module")
def exports(deploy_exports):
    return deploy_exports


def reference(ws: Path, name: str, obs: dict, noise: np.ndarray):
    ckpt, solver, steps = SETTINGS[name]
    policy = Policy.load(ws / ckpt)
    out = policy.predict_action(obs, solver=solver, steps=steps, noise=torch.from_numpy(noise))
    return out.action.numpy(), out.action_pred.numpy()


def run_onnx(directory: Path, obs: dict, noise: np.ndarray):
    import onnxruntime as ort

    meta = load_metadata(directory)
    session = ort.InferenceSession(str(directory / meta["file"]), providers=["CPUExecutionProvider"])
    feeds = {name: obs[key].astype(np.float32) for name, key in
             zip(meta["onnx_input_names"], meta["inputs"][:-1])}
    return session.run(["action", "action_pred"], {**feeds, "noise": noise})


def run_torchscript(directory: Path, obs: dict, noise: np.ndarray):
    meta = load_metadata(directory)
    module = torch.jit.load(str(directory / meta["file"]))
    with torch.inference_mode():
        action, chunk = module(*[torch.from_numpy(obs[k].astype(np.float32)) for k in meta["inputs"][:-1]],
                               torch.from_numpy(noise))
    return action.numpy(), chunk.numpy()


RUN = {"onnx": run_onnx, "torchscript": run_torchscript}


@pytest.mark.parametrize("fmt", ["onnx", "torchscript"])
@pytest.mark.parametrize("name", list(SETTINGS))
def test_parity_with_predict_action_on_100_validation_windows(ws, exports, name, fmt):
    directory = exports(name, fmt)
    meta = load_metadata(directory)
    policy = Policy.load(ws / SETTINGS[name][0])
    obs = validation_windows(policy, ws / "dataset.zarr", 100)
    assert len(obs["state"]) == 100
    noise = np.random.default_rng(0).standard_normal((100, 16, 2), dtype=np.float32)
    want_action, want_chunk = reference(ws, name, obs, noise)
    action, chunk = RUN[fmt](directory, obs, noise)
    assert chunk.shape == (100, 16, 2) and action.shape == (100, 8, 2)
    diff = np.abs(normalize_action(meta, chunk) - normalize_action(meta, want_chunk)).max()
    assert diff <= TOLERANCE, f"{name} {fmt}: max |diff| {diff:.2e} normalized"
    # the normalization inside the artifact is the checkpoint's: the chunk is in robot units
    assert np.abs(want_chunk).max() > 10 and np.abs(chunk - want_chunk).max() < 1e-3
    start, stop = meta["execute"]["start"], meta["execute"]["stop"]
    np.testing.assert_array_equal(action, chunk[:, start:stop])
    # one observation (the robot's case) gives the same answer as inside the batch
    one_action, _ = RUN[fmt](directory, {k: v[7:8] for k, v in obs.items()}, noise[7:8])
    assert np.abs(normalize_action(meta, one_action) - normalize_action(meta, want_action[7:8])).max() <= TOLERANCE
    # the noise is an input, not a constant: another noise, another chunk
    other, _ = RUN[fmt](directory, {k: v[:4] for k, v in obs.items()}, noise[4:8])
    assert np.abs(other - action[:4]).max() > 1e-3


def test_metadata_describes_the_inputs_outputs_and_timing(ws, exports):
    meta = json.loads((exports("one-step", "onnx") / "metadata.json").read_text())
    assert meta["format"] == "onnx" and meta["file"] == "policy.onnx"
    assert meta["kind"] == "sefa_one_step" and (meta["solver"], meta["steps"], meta["nfe"]) == ("euler", 1, 1)
    assert meta["inputs"] == ["keypoint", "state", "noise"]
    assert meta["obs"] == {"keypoint": {"type": "low_dim", "shape": [2, 9, 2], "dtype": "float32"},
                           "state": {"type": "low_dim", "shape": [2, 5], "dtype": "float32",
                                     "dims": [0, 2]}}
    assert meta["noise"]["shape"] == [16, 2] and meta["outputs"]["action"]["shape"] == [8, 2]
    assert (meta["n_obs_steps"], meta["n_action_steps"], meta["horizon"]) == (2, 8, 16)
    assert meta["execute"] == {"start": 1, "stop": 9} and meta["fps"] == 10.0
    # the default: opset 20 stamped IR 9 (not the exporter's IR 10), onnxruntime 1.17 loads it
    assert (meta["onnx_opset"], meta["onnx_ir_version"], meta["min_onnxruntime"]) == (20, 9, "1.17")
    flow = load_metadata(exports("euler-4", "torchscript"))
    assert flow["kind"] == "base_flow" and (flow["solver"], flow["steps"], flow["nfe"]) == ("euler", 4, 4)
    assert flow["file"] == "policy.pt" and (exports("euler-4", "torchscript") / "policy.pt").is_file()


def test_artifacts_run_without_sefa(ws, exports, tmp_path):
    """A fresh interpreter (`python -I`, in an empty directory) that refuses to import any sefa
    module loads the TorchScript file with torch alone and the ONNX file with onnxruntime
    alone, and gets the in-process results."""
    ts, onnx = exports("one-step", "torchscript"), exports("one-step", "onnx")
    policy = Policy.load(ws / "distill")
    obs = validation_windows(policy, ws / "dataset.zarr", 5)
    noise = np.random.default_rng(1).standard_normal((5, 16, 2), dtype=np.float32)
    np.savez(tmp_path / "inputs.npz", keypoint=obs["keypoint"].astype(np.float32),
             state=obs["state"].astype(np.float32), noise=noise)
    script = tmp_path / "robot.py"
    script.write_text(textwrap.dedent(f"""
        import sys
        class Blocker:
            def find_spec(self, name, path=None, target=None):
                if name.split(".")[0].startswith("sefa") or name.split(".")[0] in ("cli", "pipelines"):
                    raise ImportError("blocked: " + name)
        sys.meta_path.insert(0, Blocker())
        import numpy as np, torch, onnxruntime
        try:
            import sefa_model
        except ImportError:
            pass
        else:
            raise SystemExit("the blocker let sefa_model through")
        x = np.load("inputs.npz")
        module = torch.jit.load({str(ts / "policy.pt")!r})
        ts = module(torch.from_numpy(x["keypoint"]), torch.from_numpy(x["state"]),
                    torch.from_numpy(x["noise"]))[1].detach().numpy()
        s = onnxruntime.InferenceSession({str(onnx / "policy.onnx")!r})
        ox = s.run(["action_pred"], {{"keypoint": x["keypoint"], "state": x["state"],
                                      "noise": x["noise"]}})[0]
        np.savez("outputs.npz", ts=ts, onnx=ox)
        print("loaded", sorted(m for m in sys.modules if m.startswith("sefa")))
    """))
    r = subprocess.run([sys.executable, "-I", str(script)], cwd=tmp_path, capture_output=True,
                       text=True, env={"PATH": "/usr/bin:/bin"})
    assert r.returncode == 0, r.stderr[-3000:]
    assert "loaded []" in r.stdout
    out = np.load(tmp_path / "outputs.npz")
    _, want = reference(ws, "one-step", obs, noise)
    np.testing.assert_allclose(out["ts"], want, atol=1e-3)
    np.testing.assert_allclose(out["onnx"], want, atol=1e-3)


@pytest.mark.parametrize("encoder", ["small", "resnet18"])
def test_image_policy_exports_with_its_encoder(shared_data, tmp_path, encoder):
    """Raw uint8 HWC frames in: the image encoder (center crop at eval) inside the artifact."""
    import zarr

    from sefa_data.ingest import IngestOptions, ingest
    from sefa_model.config import load_train_config
    from sefa_model.train.loop import train

    src = zarr.open_group(str(shared_data / "pusht_cchi_v7_replay.zarr"), mode="r")
    ends = src["meta/episode_ends"][:2]
    small = tmp_path / "small.zarr"  # the first two real episodes, written with zarr
    root = zarr.open_group(str(small), mode="w", zarr_format=2)
    for key in ("img", "state", "action"):
        root.create_array(f"data/{key}", data=src["data"][key][: ends[-1]])
    root.create_array("meta/episode_ends", data=ends)
    ingest([small], tmp_path / "s.zarr", IngestOptions(fps=10))
    cfg = load_train_config(None, [
        "shape_meta.obs.img.type=rgb", "shape_meta.obs.state.dims=[0,2]", "policy.head=mlp",
        "policy.crop_shape=[84,84]", "policy.mlp_hidden_dims=[64,64]", "policy.image_feature_dim=16",
        "training.batch_size=8", "training.max_steps=2", "training.val_every=2",
        "training.val_sample_windows=2", "training.val_batches=1", "flow.solver=euler", "flow.steps=2",
        f"policy.image_encoder={encoder}"])
    train(cfg, tmp_path / "run", tmp_path / "s.zarr")
    policy = Policy.load(tmp_path / "run")
    obs = validation_windows(policy, tmp_path / "s.zarr", 6)
    assert obs["img"].dtype == np.uint8 and obs["img"].shape[1:] == (2, 96, 96, 3)
    noise = np.random.default_rng(2).standard_normal((len(obs["img"]), 16, 2), dtype=np.float32)
    want = policy.predict_action(obs, noise=torch.from_numpy(noise)).action_pred.numpy()
    for fmt in ("torchscript", "onnx"):
        need(fmt)
        out = export_policy(tmp_path / "run", tmp_path / fmt, fmt=fmt)
        assert out["obs"]["img"] == {"type": "rgb", "shape": [2, 96, 96, 3], "dtype": "uint8"}
        if fmt == "onnx":
            import onnxruntime as ort

            session = ort.InferenceSession(str(tmp_path / fmt / "policy.onnx"))
            chunk = session.run(["action_pred"], {"img": obs["img"], "state": obs["state"].astype(np.float32),
                                                  "noise": noise})[0]
        else:
            _, chunk = run_torchscript(tmp_path / fmt, obs, noise)
        diff = np.abs(normalize_action(out, chunk) - normalize_action(out, want)).max()
        assert diff <= TOLERANCE, f"{fmt}: {diff:.2e}"


def test_bad_exports_are_one_line_errors_and_leave_nothing(ws, tmp_path):
    r = sefa("export", ws / "flow", "--out", tmp_path / "a", "--json", check=False)
    assert r.returncode == 1 and r.stderr.count("\n") == 1 and r.stderr.startswith("error: ")
    assert "rk45" in r.stderr and "adaptive" in r.stderr and "--solver euler" in r.stderr
    with pytest.raises(SefaInputError, match="unknown export format 'tflite'"):
        export_policy(ws / "distill", tmp_path / "b", fmt="tflite")
    (tmp_path / "c").mkdir()
    (tmp_path / "c" / "mine.txt").write_text("keep me")
    with pytest.raises(SefaInputError, match="not a sefa export"):
        export_policy(ws / "distill", tmp_path / "c", fmt="torchscript")
    assert (tmp_path / "c" / "mine.txt").read_text() == "keep me"
    with pytest.raises(SefaInputError, match="no such checkpoint"):
        export_policy(tmp_path / "nothing", tmp_path / "d", fmt="torchscript")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c"]  # no half-written export
    with pytest.raises(SefaInputError, match="no metadata.json"):
        load_metadata(tmp_path / "c")


def test_cli_exports_and_replaces_an_earlier_export(ws, tmp_path):
    out = tmp_path / "deploy"
    r = sefa("export", ws / "flow", "--format", "torchscript", "--solver", "euler", "--steps", "2",
             "--out", out, "--json")
    meta = json.loads(r.stdout)
    assert meta["nfe"] == 2 and meta["out"] == str(out) and (out / "policy.pt").is_file()
    export_policy(ws / "distill", out, fmt="torchscript", fps=15)
    meta = load_metadata(out)
    assert meta["kind"] == "sefa_one_step" and meta["fps"] == 15.0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["deploy"]


def test_min_onnxruntime_follows_its_compatibility_table():
    from sefa_deploy.export import OPSETS, ir_version_of, min_onnxruntime

    assert [(o, ir_version_of(o), min_onnxruntime(o, ir_version_of(o))) for o in OPSETS] == [
        (18, 8, "1.14"), (19, 9, "1.16"), (20, 9, "1.17"), (21, 10, "1.18")]
    assert min_onnxruntime(19, 8) == "1.15"  # 1.15 implements opset 19 but loads IR 8 only


@pytest.mark.parametrize("opset", [18, 21])
def test_export_at_each_end_of_the_opset_range_loads_and_matches(ws, tmp_path, opset):
    """The file says what metadata.json says, and onnxruntime runs it to predict_action's
    answer on real windows."""
    import onnx

    need("onnx")
    meta = export_policy(ws / "distill", tmp_path / "x", fmt="onnx", opset=opset)
    model = onnx.load(str(tmp_path / "x" / "policy.onnx"))
    assert [(o.domain, o.version) for o in model.opset_import] == [("", opset)]
    assert model.ir_version == meta["onnx_ir_version"] == {18: 8, 21: 10}[opset]
    assert meta["onnx_opset"] == opset and meta["min_onnxruntime"] == {18: "1.14", 21: "1.18"}[opset]
    policy = Policy.load(ws / "distill")
    obs = validation_windows(policy, ws / "dataset.zarr", 20)
    noise = np.random.default_rng(1).standard_normal((len(obs["state"]), 16, 2), dtype=np.float32)
    _, chunk = run_onnx(tmp_path / "x", obs, noise)
    _, want = reference(ws, "one-step", obs, noise)
    assert np.abs(normalize_action(meta, chunk) - normalize_action(meta, want)).max() <= TOLERANCE


BAD_OPSETS = [(["--opset", "17"], "--opset: 17 is too small (valid: an integer in [18, 21])"),
              (["--opset", "22"], "--opset: 22 is too large (valid: an integer in [18, 21])")]


@pytest.mark.parametrize("args,line", BAD_OPSETS, ids=[" ".join(a) for a, _ in BAD_OPSETS])
def test_an_opset_out_of_range_is_one_line_before_any_work(args, line, tmp_path):
    r = sefa("export", tmp_path / "no-such-checkpoint", "--out", tmp_path / "o", *args,
             check=False)
    assert r.returncode == 1 and r.stderr == f"error: {line}\n"


def test_an_opset_for_torchscript_is_refused(ws, tmp_path):
    with pytest.raises(SefaInputError, match="--opset: an opset is an ONNX setting"):
        export_policy(ws / "distill", tmp_path / "t", fmt="torchscript", opset=18)
    with pytest.raises(SefaInputError, match="--opset: 17 is not supported"):
        export_policy(ws / "distill", tmp_path / "t", fmt="onnx", opset=17)


def _offset_artifact(monkeypatch, pixels: float) -> None:
    """Fault injection: the exported module's actions moved by `pixels` action units, inside
    the artifact only (the checkpoint's predict_action is untouched)."""
    from sefa_deploy import export as export_module

    forward = export_module.ExportedPolicy.forward

    def shifted(self, *inputs):
        action, chunk = forward(self, *inputs)
        return action + pixels, chunk + pixels
    monkeypatch.setattr(export_module.ExportedPolicy, "forward", shifted)


def test_the_parity_check_is_relative_to_the_actions_range(ws, tmp_path, monkeypatch):
    """Push-T's actions are pixels (a range of about 500): a float32-sized gap of 0.01 px is
    1e-5 of that range and is published (an absolute 1e-3 bound refused it); a real fault of
    20 px is refused, naming the gap in both units, and --tolerance moves the bound."""
    policy = Policy.load(ws / "distill")
    scale = policy.normalizer.params["action"].scale
    _offset_artifact(monkeypatch, 0.01)
    meta = export_policy(ws / "distill", tmp_path / "ok", fmt="torchscript")
    assert (tmp_path / "ok" / "policy.pt").is_file() and meta["kind"] == "sefa_one_step"
    assert 0.01 * float(np.abs(scale).max()) / 2 < 1e-4  # the gap that was published

    _offset_artifact(monkeypatch, 20.0)
    with pytest.raises(SefaInputError) as e:
        export_policy(ws / "distill", tmp_path / "bad", fmt="torchscript")
    line = e.value.line()
    rel = 20.0 * float(np.abs(scale).max()) / 2
    assert "differs from the checkpoint by 20 in action units" in line, line
    assert f"{rel:.3g} of the action's range" in line and "--tolerance" in line, line
    assert not (tmp_path / "bad").exists()
    # a looser tolerance (the user's call) publishes it
    export_policy(ws / "distill", tmp_path / "loose", fmt="torchscript", tolerance=0.5)
    assert (tmp_path / "loose" / "metadata.json").is_file()


def test_the_tolerance_flag_sets_the_bound_and_is_range_checked(ws, tmp_path):
    r = sefa("export", ws / "distill", "--out", tmp_path / "ok", "--tolerance", "0.01")
    assert "(tolerance 0.01)" in r.stderr and (tmp_path / "ok" / "policy.onnx").is_file()
    r = sefa("export", ws / "distill", "--out", tmp_path / "x", "--tolerance", "2", check=False)
    assert r.returncode == 1 and r.stderr.startswith("error: ") and "--tolerance" in r.stderr
    assert r.stderr.count("\n") == 1 and not (tmp_path / "x").exists()
