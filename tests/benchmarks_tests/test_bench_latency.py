"""`sefa bench latency` on tiny checkpoints (a flow and the diffusion baseline) trained on the
real Push-T demonstrations: the rows, their NFE per setting, the JSON, and bad targets."""

from __future__ import annotations

import json
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from cli_inprocess import run_cli
from sefa_data.errors import SefaInputError
from sefa_data.ingest import IngestOptions, ingest
from sefa_model.config import load_train_config
from sefa_model.eval.latency import bench_latency, example_observation, parse_target, time_calls
from sefa_model.policy.artifact import Policy
from sefa_model.train.loop import train

REPO = Path(__file__).resolve().parents[2]
TINY = ["shape_meta.obs.keypoint.type=low_dim", "shape_meta.obs.state.dims=[0,2]",
        "policy.head=mlp", "policy.mlp_hidden_dims=[64,64]", "policy.time_embed_dim=32",
        "training.batch_size=64", "training.max_steps=10", "training.val_every=10",
        "training.val_sample_windows=8", "training.val_batches=1"]


@pytest.fixture(scope="module")
def workspace(shared_data, tmp_path_factory) -> Path:
    ws = tmp_path_factory.mktemp("bench")
    ingest([shared_data / "pusht_cchi_v7_replay.zarr"], ws / "dataset.zarr",
           IngestOptions(fps=10, keys=["keypoint", "state", "action"]))
    train(load_train_config(None, TINY), ws / "flow", ws / "dataset.zarr")
    train(load_train_config(None, TINY + ["objective=ddpm"]), ws / "ddpm", ws / "dataset.zarr")
    return ws


def test_parse_target():
    assert parse_target("runs/a/train") == ("runs/a/train", None, None)
    assert parse_target("runs/a/train@rk45") == ("runs/a/train", "rk45", None)
    assert parse_target("ddpm@ddim-10") == ("ddpm", "ddim", 10)
    with pytest.raises(SefaInputError, match="SOLVER-STEPS"):
        parse_target("ddpm@ddim-ten")


def test_time_calls_warms_up_interleaves_and_stops_slow_settings_early():
    order = []
    seconds = time_calls({"slow": lambda: (order.append("slow"), time.sleep(0.002)),
                          "fast": lambda: order.append("fast")},
                         warmup=3, calls=1000, max_seconds=0.01, sync=lambda: None)
    # at least 20 timed rounds after 3 untimed ones, the two functions taking turns
    assert len(seconds["slow"]) == len(seconds["fast"]) == 20
    assert order == ["slow", "fast"] * 23
    assert (seconds["slow"] >= 0.002).all() and np.median(seconds["fast"]) < 0.002


def test_every_setting_gets_its_nfe_percentiles_and_the_forward_floor(workspace):
    ws = workspace
    targets = [f"{ws}/flow@rk45", f"{ws}/flow@euler-1", f"{ws}/flow@euler-4", f"{ws}/ddpm",
               f"{ws}/ddpm@ddim-3"]
    out = bench_latency(targets, store=ws / "dataset.zarr", calls=5, warmup=1, max_seconds=5)
    rows = {r["target"]: r for r in out["rows"]}
    assert [r["target"] for r in out["rows"]] == targets
    assert [rows[t]["setting"] for t in targets] == ["rk45", "euler-1", "euler-4", "ddpm-100", "ddim-3"]
    assert [rows[t]["nfe"] for t in targets[1:]] == [1, 4, 100, 3]
    assert rows[targets[0]]["nfe"] >= 6  # at least one Dormand-Prince step
    assert {rows[t]["kind"] for t in targets} == {"base_flow", "ddpm"}
    for r in out["rows"]:
        assert 0 < r["p50_ms"] <= r["p90_ms"] <= r["p99_ms"]
        assert r["calls"] == 5 and r["forward_ms"] > 0 and r["encoder_ms"] > 0 and r["head_ms"] > 0
        assert r["ratio_to_forward"] == pytest.approx(r["p50_ms"] / r["forward_ms"])
        assert "window" in r["obs_source"]
    # a 100-step sampler is slower than one step of the same size of network
    assert rows[f"{ws}/ddpm"]["p50_ms"] > rows[f"{ws}/flow@euler-1"]["p50_ms"]
    assert {"cpu", "cores", "torch", "torch_threads"} <= set(out["machine"])


def test_without_a_store_the_observation_is_the_normalizers_centre(workspace):
    policy = Policy.load(workspace / "flow")
    obs, source = example_observation(policy, None)
    assert "centre" in source
    assert obs["state"].shape == (1, 2, 5) and obs["keypoint"].shape == (1, 2, 9, 2)
    prepared = policy.prepare_obs(obs)
    for key in ("state", "keypoint"):
        np.testing.assert_allclose(prepared[key].numpy(), 0, atol=1e-5)  # normalized: the centre
    assert (obs["state"][..., 2:] == 0).all()  # dims the policy does not see stay zero


def sefa(ws: Path, *args) -> subprocess.CompletedProcess:
    """`sefa ARGS -w WS` in-process through sefa_cli.main.main (tests/cli_inprocess.py)."""
    return run_cli(*args, "-w", ws, cwd=REPO)


def test_cli_json_table_and_bad_targets(workspace):
    ws = workspace
    r = sefa(ws, "bench", "latency", ws / "flow", f"{ws / 'ddpm'}@ddim-2", "--calls", "3",
             "--warmup", "1", "--passes", "2", "--json")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["passes"] == 2 and len(out["rows"]) == 2  # the fastest pass of each target
    assert out["rows"][0]["nfe"] > 1 and out["rows"][1]["nfe"] == 2
    assert out["rows"][0]["setting"] == "rk45" and out["batch"] == 1
    r = sefa(ws, "bench", "latency", f"{ws / 'flow'}@euler-1", "--calls", "3", "--warmup", "1")
    assert r.returncode == 0, r.stderr
    assert "p50" in r.stdout and "bare forward" in r.stdout and "euler-1" in r.stdout
    r = sefa(ws, "bench", "latency", f"{ws / 'flow'}@warp-2")
    assert r.returncode == 1 and r.stderr.count("\n") == 1 and "solver 'warp'" in r.stderr
    r = sefa(ws, "bench", "latency", ws / "nothing")
    assert r.returncode == 1 and r.stderr.count("\n") == 1 and "nothing" in r.stderr


def test_threads_from_the_option_or_sefa_yaml_and_recorded(workspace):
    """--threads sets torch's threads for the timing (the report says how many); without it the
    workspace's sefa.yaml `threads` does, as for every other command."""
    import torch

    ws, before = workspace, torch.get_num_threads()
    try:
        r = sefa(ws, "bench", "latency", f"{ws / 'flow'}@euler-1", "--calls", "3", "--warmup",
                 "1", "--threads", "1", "--json")
        assert r.returncode == 0, r.stderr
        assert json.loads(r.stdout)["threads"] == 1
        torch.set_num_threads(2)
        (ws / "sefa.yaml").write_text("threads: 1\n")
        r = sefa(ws, "bench", "latency", f"{ws / 'flow'}@euler-1", "--calls", "3", "--warmup",
                 "1", "--json")
        assert r.returncode == 0, r.stderr
        assert json.loads(r.stdout)["threads"] == 1
    finally:
        (ws / "sefa.yaml").unlink(missing_ok=True)
        torch.set_num_threads(before)


def test_a_wide_spread_of_timings_is_said_with_the_load():
    from sefa_model.eval.latency import spread_note

    row = {"target": "distill", "p50_ms": 8.0, "p99_ms": 456.0}
    assert spread_note(row, 6.4, 2) == (
        "warning: distill: p99 is 57.0x p50 (456 vs 8 ms); the machine is busy (load 6.4 on 2 "
        "cores): the numbers include other work; rerun with --passes 3 (each target keeps its "
        "fastest pass) and --threads 1 on a shared CPU")
    assert spread_note({**row, "p99_ms": 12.0}, 6.4, 2) is None
    assert "busy" not in spread_note(row, 0.5, 2)


def test_decisions_at_1_to_64_samples_beside_ddim10_and_each_executions_cost(workspace):
    """`--samples 1,4,16,64`: one decision of N chunks per target and N (the flow at Euler-1,
    the diffusion baseline at DDIM-10), and every default execution's cost per control step
    at the store's 10 Hz from the decision at its N."""
    r = run_cli("bench", "latency", f"{workspace / 'flow'}@euler-1", f"{workspace / 'ddpm'}@ddim-10",
                "--samples", "64,1,16,4", "--calls", "5", "--warmup", "1", "--max-seconds", "1",
                "--store", workspace / "dataset.zarr", "--json")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["sample_sizes"] == [1, 4, 16, 64] and out["fps"] == 10
    got = [(d["target"].rsplit("@")[1], d["samples"]) for d in out["decisions"]]
    assert got == [(s, n) for s in ("euler-1", "ddim-10") for n in (1, 4, 16, 64)]
    assert all(d["p50_ms"] <= d["p99_ms"] for d in out["decisions"])
    flow = {e["execution"]: e for e in out["executions"] if e["target"].endswith("euler-1")}
    one = next(d for d in out["decisions"] if d["samples"] == 1 and "euler" in d["target"])
    assert flow["receding K=4"]["mean_step_ms"] == pytest.approx(one["p50_ms"] / 4)
    assert flow["receding K=4"]["period_ms"] == 100.0 and "coherent K=1 N=16" in flow
    r = run_cli("bench", "latency", f"{workspace / 'flow'}@euler-1", "--samples", "1,x")
    assert r.returncode == 1 and r.stderr.startswith("error: --samples: '1,x' is not a comma")


def test_a_checkpoint_is_looked_for_in_the_workspace_as_eval_and_export_look(workspace):
    """`sefa bench latency flow -w ws` from another folder times ws/flow (it failed with
    "flow: no such checkpoint" where eval, export and serve found it)."""
    r = run_cli("bench", "latency", "flow@euler-1", "--calls", "3", "--warmup", "1", "--json",
                "-w", workspace, cwd=REPO)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["rows"][0]["checkpoint"].startswith(str(workspace / "flow"))


def test_without_samples_the_executions_of_one_chunk_are_judged_at_the_control_rate(workspace):
    """At --fps the table says, for each target, which one-chunk executions fit the period
    (receding horizon at every replanning period, ACT's ensembling) from the batch-1 p50
    (mean per step) and p99 (the worst step: a whole decision), and one line names them."""
    from sefa_model.eval.latency import fit_summary, single_chunk_costs

    costs = single_chunk_costs(8, decision_ms=20.0, worst_ms=40.0, fps=30)
    assert [(c["execution"], c["mean_step_ms"], c["fits"]) for c in costs] == [
        ("receding K=1", 20.0, False), ("receding K=2", 10.0, False),
        ("receding K=4", 5.0, False), ("receding K=8", 2.5, False), ("ensemble K=1", 20.0, False)]
    fast = single_chunk_costs(8, decision_ms=1.0, worst_ms=2.0, fps=30)
    assert all(c["fits"] for c in fast) and fast[0]["period_ms"] == pytest.approx(1000 / 30)
    lines = fit_summary([{"target": "distill", **c} for c in costs + fast[:1]], 30)
    assert lines == ["distill at 30 Hz (33.3 ms a step): fits: receding K=1; over the period at "
                     "its worst step: receding K=1 (40 ms), receding K=2 (40 ms), receding K=4 "
                     "(40 ms), receding K=8 (40 ms), ensemble K=1 (40 ms)"]
    assert fit_summary(costs, None) == []
    r = run_cli("bench", "latency", f"{workspace / 'flow'}@euler-1", "--calls", "3", "--warmup",
                "1", "--fps", "1000000", cwd=REPO)
    assert r.returncode == 0, r.stderr
    text = " ".join(r.stdout.split())
    assert "each execution per control step at 1e+06 Hz" in text
    assert "at 1e+06 Hz (0.001 ms a step): no execution fits; over the period" in text
    r = run_cli("bench", "latency", f"{workspace / 'flow'}@euler-1", "--calls", "3", "--warmup",
                "1", "--json", cwd=REPO)  # no --fps, no store given: no rate, nothing judged
    assert {e["fits"] for e in json.loads(r.stdout)["executions"]} == {None}
