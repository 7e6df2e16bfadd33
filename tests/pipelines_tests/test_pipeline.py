"""The SeFA stages end to end through the CLI on a small Push-T configuration (issue 4):
ingest, train, reflow (2 iterations), align, distill in one workspace; caching; a killed stage.

The commands run in-process through sefa_cli.main.main (tests/cli_inprocess.py); the killed stage and
the server that must refuse damaged weights run in real child processes."""

from __future__ import annotations

import json
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from cli_inprocess import run_cli

REPO = Path(__file__).resolve().parents[2]
SMALL_TRAIN = [
    "shape_meta.obs.keypoint.type=low_dim", "shape_meta.obs.state.dims=[0,2]",
    "policy.head=mlp", "policy.mlp_hidden_dims=[64,64]", "policy.time_embed_dim=32",
    "training.max_steps=40", "training.batch_size=64", "training.lr=1e-3",
    "training.lr_warmup_steps=5", "training.val_every=20", "training.checkpoint_every=20",
    "training.val_batches=1", "training.val_sample_windows=16",
]


def sefa(ws: Path, *args) -> subprocess.CompletedProcess:
    """`sefa ARGS -w WS`, in-process through sefa_cli.main.main (tests/cli_inprocess.py); the killed
    stage and the server run in real child processes below."""
    r = run_cli(*args, "-w", ws, cwd=REPO)
    assert r.returncode == 0, r.stderr[-3000:]
    return r


def ran(r: subprocess.CompletedProcess) -> list[str]:
    return [line.split(":")[0] for line in r.stderr.splitlines() if ": running (" in line]


@pytest.fixture(scope="module")
def workspace(shared_data, tmp_path_factory) -> Path:
    ws = tmp_path_factory.mktemp("ws")
    sefa(ws, "ingest", shared_data / "pusht_cchi_v7_replay.zarr", "--fps", "10",
         "--key", "keypoint", "--key", "state", "--key", "action")
    sefa(ws, "train", *SMALL_TRAIN)
    sefa(ws, "reflow", "--iters", "2", "--max-windows", "48", "--samples", "3")
    r = sefa(ws, "align", "--eps", "0.05")
    assert "replaced" in r.stdout and "<- eps=0.05" in r.stdout
    sefa(ws, "distill")
    return ws


def test_every_stage_produced_its_artifact(workspace):
    import zarr

    for artifact in ("train", "reflow/iter_1", "reflow/iter_2", "align", "distill"):
        manifest = json.loads((workspace / artifact / "manifest.json").read_text())
        assert manifest["status"] == "complete", artifact
    couplings = zarr.open_group(str(workspace / "reflow/iter_2/couplings.zarr"), mode="r")
    assert couplings["noise"].shape == couplings["action"].shape == (48 * 3, 16, 2)
    assert couplings.attrs["solver"] == "rk45" and couplings.attrs["nfe"] > 0
    assert (workspace / "reflow/iter_2/flow/checkpoints/latest/model.safetensors").exists()
    aligned = zarr.open_group(str(workspace / "align/aligned.zarr"), mode="r")
    d, rep = aligned["distance"][:], aligned["replaced"][:]
    np.testing.assert_array_equal(rep, d < 0.05)
    assert aligned.attrs["eps"] == 0.05 and "per-step L2" in aligned.attrs["metric"]
    cfg = json.loads((workspace / "distill/checkpoints/latest/config.json").read_text())
    # a student whose alignment replaced nothing is plain reflow (issue 25): eps 0.05 is far
    # below this tiny flow's distances
    assert cfg["kind"] == ("sefa_one_step" if rep.any() else "reflow_one_step")


def test_second_run_is_all_cached_and_eps_change_reruns_align_and_distill_only(workspace):
    r = sefa(workspace, "run")
    assert ran(r) == []
    for stage in ("train", "reflow iter 1", "reflow iter 2", "align", "distill"):
        assert f"{stage}: cached" in r.stderr
    sefa(workspace, "align", "--eps", "0.2")  # reruns align; distill is now stale
    status = sefa(workspace, "status", "--json")
    states = {row["stage"]: row["state"] for row in json.loads(status.stdout)["rows"]
              if row["stage"] not in ("ingest", "eval")}
    assert states == {"train": "cached", "reflow iter 1": "cached", "reflow iter 2": "cached",
                      "align": "cached", "distill": "stale"}
    r = sefa(workspace, "run")
    assert ran(r) == ["distill"]


def test_run_says_what_alignment_did_as_align_does(workspace):
    """`sefa run` printed nothing of what alignment replaced; now, when its align stage runs,
    the same report as `sefa align`: the fraction replaced, the histogram marking eps, the
    quantiles (and the warnings)."""
    r = sefa(workspace, "run", "--force", "align")
    assert "align" in ran(r)
    assert re.search(r"^replaced [\d.]+% of 144 couplings \(eps 0\.2;", r.stdout, re.M), r.stdout
    assert "<- eps=0.2" in r.stdout and "distance quantiles: q0 " in r.stdout
    r = sefa(workspace, "run")  # nothing ran: nothing to report again
    assert ran(r) == [] and "distance quantiles" not in r.stdout


def test_distilled_policy_makes_exactly_one_network_call(workspace, shared_data):
    from sefa_model.policy.artifact import Policy

    policy = Policy.load(workspace / "distill")
    calls = {"head": 0, "encoder": 0}
    policy.model.head.register_forward_hook(lambda *a: calls.__setitem__("head", calls["head"] + 1))
    policy.model.obs_encoder.register_forward_hook(
        lambda *a: calls.__setitem__("encoder", calls["encoder"] + 1))
    obs = {"keypoint": np.zeros((2, 9, 2), np.float32), "state": np.zeros((2, 5), np.float32)}
    out = policy.predict_action(obs)
    assert calls == {"head": 1, "encoder": 1} and out.nfe == 1
    assert out.action.shape == (1, 8, 2)


def test_killed_stage_leaves_workspace_valid_and_only_it_reruns(workspace):
    sefa(workspace, "align", "--eps", "0.1")  # distill is stale again
    before = (workspace / "distill" / "manifest.json").read_bytes()
    proc = subprocess.Popen([sys.executable, "-m", "sefa_cli.main", "run", "-w", str(workspace)],
                            cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.time() + 120
    while time.time() < deadline and not list(workspace.glob("runs/distill/.*.partial")):
        time.sleep(0.005)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=30)
    assert (workspace / "distill" / "manifest.json").read_bytes() == before  # the old one, intact
    status = {row["stage"]: row["state"]
              for row in json.loads(sefa(workspace, "status", "--json").stdout)["rows"]}
    assert status["distill"] == "stale" and status["align"] == "cached"
    r = sefa(workspace, "run")
    assert ran(r) == ["distill"]
    assert not list(workspace.glob("runs/distill/.*.partial"))


def test_offline_eval_compares_the_stages(workspace):
    rows = json.loads(sefa(workspace, "eval", "--offline", "--windows", "32", "--samples", "4",
                           "--json").stdout)
    kinds = {r["kind"]: r for r in rows}
    student = json.loads((workspace / "distill/checkpoints/latest/config.json").read_text())["kind"]
    assert set(kinds) == {"base_flow", "reflow", student}
    assert kinds[student]["nfe"] == 1 and kinds["base_flow"]["nfe"] > 6
    for r in rows:
        assert np.isfinite([r["action_mse"], r["spread"], r["expert_spread"]]).all()
        assert r["action_mse_best_of_k"] <= r["action_mse"] + 1e-9
        assert r["windows"] == 32 and r["split"] == "valid"


def test_spread_and_nearest_windows_on_constructed_data():
    from sefa_model.eval.offline import chunk_spread, nearest_windows

    same = np.ones((3, 5, 4, 2))
    assert chunk_spread(same).tolist() == [0.0, 0.0, 0.0]
    two = np.zeros((1, 2, 4, 2))
    two[0, 1] = 2.0  # samples 0 and 2: per-element std 1
    assert chunk_spread(two).tolist() == [1.0]
    pool = np.array([[0.0], [10.0], [1.0], [11.0]])
    near = nearest_windows(np.array([[0.2], [10.4]]), pool, 2)
    assert sorted(near[0].tolist()) == [0, 2] and sorted(near[1].tolist()) == [1, 3]


def test_reflow_with_per_sample_steps_matches_each_chunk_solved_alone(workspace, tmp_path):
    """CouplingConfig.solver="rk45-ps": every chunk of a block gets its own step size, so a
    chunk's coupling is what solving that chunk alone gives (up to the network's batched
    matmuls rounding a row differently by batch size), and finished chunks stop costing."""
    import torch
    import zarr

    from sefa_data.store.zarr_store import EpisodeStore
    from sefa_model.policy.artifact import Policy
    from sefa_model.sefa.reflow import CouplingConfig, generate_couplings, window_subset
    from sefa_model.flow.solvers import solve
    from sefa_model.data.windows import PolicyData

    policy = Policy.load(workspace / "train")
    store = workspace / "dataset.zarr"
    cfg = CouplingConfig(samples_per_window=3, solver="rk45-ps", max_windows=6, batch_windows=6)
    summary = generate_couplings(policy, store, tmp_path / "c.zarr", cfg)
    root = zarr.open_group(str(tmp_path / "c.zarr"), mode="r")
    assert root.attrs["solver"] == "rk45-ps" and summary["n"] == 18
    assert summary["sample_evals"] < summary["nfe"] * 18  # rows left the batch as they finished
    assert summary["evals_per_coupling"] == summary["sample_evals"] / 18

    data = PolicyData(policy.cfg, EpisodeStore.open(store), policy.normalizer)
    windows = window_subset(len(data.train), 6)
    assert np.array_equal(root["window"][:], np.repeat(windows, 3))
    obs, _ = data.tensors(data.train, windows, policy.device)
    with torch.no_grad():
        cond = policy.model.encode(obs).repeat_interleave(3, dim=0)
        noise = torch.from_numpy(root["noise"][:])
        for row in (0, 7, 17):
            alone = solve(policy.model.velocity, noise[row:row + 1], "rk45-ps", t0=policy.cfg.flow.t_eps,
                          cond=cond[row:row + 1])
            # the network rounds a row differently at batch 1 than at 18 (up to ~3e-6), and the
            # step controller can amplify that to a few 1e-4 (measured: up to 4.5e-4); a shared
            # step size over the block would differ by the solver tolerance's order instead
            np.testing.assert_allclose(alone.x[0].numpy(), root["action"][row], rtol=0, atol=1e-3)

    obs2 = {"keypoint": np.zeros((2, 2, 9, 2), np.float32), "state": np.zeros((2, 2, 5), np.float32)}
    out = policy.predict_action(obs2, solver="rk45-ps")  # a batch: cond follows the rows
    assert out.action.shape == (2, 8, 2) and out.nfe > 6


def test_each_reflow_round_draws_fresh_noise_and_names_a_checkpoint_that_exists(workspace):
    """Round 2 must not re-solve the noises its flow was fitted on (issue 11)."""
    import zarr

    one = zarr.open_group(str(workspace / "reflow/iter_1/couplings.zarr"), mode="r")
    two = zarr.open_group(str(workspace / "reflow/iter_2/couplings.zarr"), mode="r")
    np.testing.assert_array_equal(one["window"][:], two["window"][:])  # the same windows
    n1, n2 = one["noise"][:], two["noise"][:]
    assert not np.isclose(n1, n2).all(axis=(1, 2)).any()  # no coupling reuses its noise
    for group in (one, two):
        assert (workspace / group.attrs["source_checkpoint"] / "config.json").is_file()
    assert two.attrs["source_checkpoint"] == "reflow/iter_2/flow/checkpoints/latest"
    # the reflowed flow and the student keep the base encoder and say so
    for ckpt in ("reflow/iter_2/flow/checkpoints/latest", "distill/checkpoints/latest"):
        meta = json.loads((workspace / ckpt / "config.json").read_text())
        assert meta["train_config"]["training"]["freeze_encoder"] is True
        assert meta["encoder"].startswith("frozen")


def test_matching_obs_alignment_uses_the_policys_view_of_the_observation(workspace, tmp_path):
    """The config takes `state` dims [0, 2]: the match features are what the policy's encoder
    sees (normalized keypoints and agent position of 2 frames), and every coupling that the
    same-window rule replaces is replaced here too (its own window always matches)."""
    import zarr

    from sefa_pipelines.stages import AlignStageConfig, StageContext, _align_run
    from sefa_data.store.zarr_store import EpisodeStore
    from sefa_model.policy.artifact import Policy
    from sefa_model.data.features import window_features
    from sefa_model.data.windows import PolicyData

    store = workspace / "dataset.zarr"
    _align_run(StageContext(workspace, store, [], "cpu"), "reflow/iter_2", AlignStageConfig(eps=0.0))(tmp_path / "d")
    distance = zarr.open_group(str(tmp_path / "d" / "aligned.zarr"), mode="r")["distance"][:]
    eps = float(np.median(distance))  # the same-window rule replaces about half
    summary = _align_run(StageContext(workspace, store, [], "cpu"), "reflow/iter_2",
                         AlignStageConfig(eps=eps, variant="matching_obs"))(tmp_path)
    same = _align_run(StageContext(workspace, store, [], "cpu"), "reflow/iter_2",
                      AlignStageConfig(eps=eps, variant="same_window"))(tmp_path / "s")
    assert summary["variant"] == "matching_obs" and summary["n"] == same["n"]
    rep = zarr.open_group(str(tmp_path / "aligned.zarr"), mode="r")["replaced"][:]
    rep_same = zarr.open_group(str(tmp_path / "s" / "aligned.zarr"), mode="r")["replaced"][:]
    assert rep_same.any() and (rep >= rep_same).all()
    policy = Policy.load(workspace / "train", device="cpu")
    data = PolicyData(policy.cfg, EpisodeStore.open(store), policy.normalizer)
    f = window_features(policy.model, data, np.arange(3), policy.device)
    assert f.shape == (3, 2 * (18 + 2))
    obs, _ = data.tensors(data.train, np.arange(3), policy.device)
    torch_state = obs["state"]  # normalized agent position, as the policy sees it
    assert torch_state.shape[-1] == 2
    np.testing.assert_array_equal(f.view(3, 2, 20)[:, :, 18:].numpy(), torch_state.numpy())


def test_couplings_report_their_drift_from_the_expert(workspace):
    """expert_drift of round 2 is the same-window alignment distance of its couplings."""
    import zarr

    from sefa_pipelines.stages import AlignStageConfig, StageContext, _align_run

    two = zarr.open_group(str(workspace / "reflow/iter_2/couplings.zarr"), mode="r")
    drift = two.attrs["expert_drift"]
    store = workspace / "dataset.zarr"
    out = workspace.parent / "drift_check"
    _align_run(StageContext(workspace, store, [], "cpu"), "reflow/iter_2", AlignStageConfig(eps=0.0))(out)
    d = zarr.open_group(str(out / "aligned.zarr"), mode="r")["distance"][:].astype(np.float64)
    assert drift["mean"] == pytest.approx(d.mean(), rel=1e-6)
    assert drift["median"] == pytest.approx(np.median(d), rel=1e-6)
    for eps, frac in drift["within"].items():
        assert frac == pytest.approx((d < float(eps)).mean())


def test_align_rounds_trains_the_next_round_on_aligned_couplings(workspace):
    """`--align-rounds`: round 1's couplings are aligned (align's eps) before round 2's flow
    trains on them; round 1 stays cached, and the training set is kept in the artifact."""
    import zarr

    one = zarr.open_group(str(workspace / "reflow/iter_1/couplings.zarr"), mode="r")
    eps = round(one.attrs["expert_drift"]["median"], 4)  # replaces about half of round 1's
    sefa(workspace, "align", "--eps", eps)
    r = sefa(workspace, "reflow", "--iters", "2", "--align-rounds")
    assert ran(r) == ["reflow iter 2"]
    manifest = json.loads((workspace / "reflow/iter_2/manifest.json").read_text())
    summary = manifest["summary"]["aligned_input"]
    assert summary["eps"] == eps and summary["couplings"].endswith("reflow/iter_1/couplings.zarr")
    aligned = zarr.open_group(str(workspace / "reflow/iter_2/trained_on_aligned.zarr"), mode="r")
    rep = aligned["replaced"][:]
    assert summary["fraction_replaced"] == pytest.approx(rep.mean()) and rep.any() and not rep.all()
    target = aligned["target"][:]
    np.testing.assert_array_equal(target[~rep], one["action"][:][~rep])  # far ones kept
    assert not np.array_equal(target[rep], one["action"][:][rep])  # near ones snapped
    meta = json.loads((workspace / "reflow/iter_2/flow/checkpoints/latest/config.json").read_text())
    assert meta["kind"] == "reflow"
    # the rounds' setting is part of round 2's cache key: turning it off goes back to the kept
    # unaligned round 2, without recomputing anything
    r = sefa(workspace, "reflow", "--no-align-rounds")
    assert ran(r) == [] and "a kept run" in r.stderr
    assert not (workspace / "reflow/iter_2/trained_on_aligned.zarr").exists()
    assert "aligned_input" not in json.loads((workspace / "reflow/iter_2/manifest.json").read_text())["summary"]


def test_a_flipped_bit_in_weights_stops_every_stage_that_reads_them(workspace, tmp_path):
    """Issue 23: one flipped exponent bit in an EMA weights file is caught by the checksums
    before reflow, distill, eval, export or serve use it: exit 1, one line naming the file,
    nothing published (the weights stay finite numbers, so only the checksum can tell)."""
    from test_finite import flip_exponent_bit, one_error_line

    ws = tmp_path / "ws"
    shutil.copytree(workspace, ws, symlinks=True)
    env = {"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin"}

    def run(*args):
        if args[0] != "serve":  # the refusals in-process; the server, which must not start, a child
            return run_cli(*args, cwd=REPO)
        return subprocess.run([sys.executable, "-m", "sefa_cli.main", *map(str, args)],
                              capture_output=True, text=True, cwd=REPO, env=env, timeout=300)

    damaged = {"train": ws / "train/checkpoints/latest/ema.safetensors",
               "reflow": ws / "reflow/iter_2/flow/checkpoints/latest/ema.safetensors",
               "distill": ws / "distill/checkpoints/latest/ema.safetensors"}
    for path in damaged.values():
        flip_exponent_bit(path)
    before = sorted(p.relative_to(ws).as_posix() for p in ws.rglob("*") if "evals" not in p.parts)
    commands = {
        # --force: a cached stage reads nothing (artifacts are keyed by their manifests)
        "reflow": (["reflow", "--iters", "2", "--max-windows", "48", "--samples", "3", "--force",
                    "-w", ws], damaged["train"]),
        "distill": (["distill", "--force", "-w", ws], damaged["reflow"]),
        "eval": (["eval", ws / "distill", "--offline", "--windows", "4", "-w", ws], damaged["distill"]),
        "export": (["export", ws / "distill", "--out", tmp_path / "export", "--format",
                    "torchscript"], damaged["distill"]),
        "serve": (["serve", ws / "distill", "--port", "0"], damaged["distill"]),
    }
    for name, (args, path) in commands.items():
        line = one_error_line(run(*args))
        assert f"{path.name}: checksum mismatch" in line and path.parent.name in line, (name, line)
    assert not (tmp_path / "export").exists()
    after = sorted(p.relative_to(ws).as_posix() for p in ws.rglob("*") if "evals" not in p.parts
                   and not p.name.startswith(".sefa") and p.parts[len(ws.parts)] != ".sefa")
    assert [p for p in after if p not in before] == []  # nothing new published
