"""Reflow says how far it is inside a block: a block of 256 windows x K noises is one batched
ODE solve that may take minutes on a CPU, and a bar that moves only when a block ends says
nothing for that long. The store is two scripted Meta-World episodes (the simulator's expert,
no download); the flow is a tiny MLP trained for a few steps."""

from __future__ import annotations

from pathlib import Path

import pytest

from sefa_data.ingest import IngestOptions, ingest
from sefa_model.config import load_train_config
from sefa_model.policy.artifact import Policy
from sefa_model.progress import listening
from sefa_model.sefa.reflow import CouplingConfig, generate_couplings
from sefa_model.train.loop import train

PRESET = Path(__file__).resolve().parents[2] / "pipelines" / "metaworld_train.yaml"
TINY_FLOW = ["policy.mlp_hidden_dims=[32,32]", "policy.time_embed_dim=16",
             "training.batch_size=32", "training.max_steps=5", "training.val_every=5",
             "training.checkpoint_every=5", "training.lr_warmup_steps=1"]


@pytest.fixture(scope="module")
def flow(tmp_path_factory) -> tuple[Policy, Path]:
    pytest.importorskip("metaworld", reason="Meta-World is not installed (sefa[sim])")
    from sefa_sim.metaworld import collect_metaworld

    tmp = tmp_path_factory.mktemp("reflow_progress")
    collect_metaworld(tmp / "demos.hdf5", "button-press", 2, seed=0)
    store = tmp / "demos.zarr"
    ingest([tmp / "demos.hdf5"], store, IngestOptions())
    train(load_train_config(PRESET, TINY_FLOW), tmp / "base", store)
    return Policy.load(tmp / "base", device="cpu"), store


def test_reflow_reports_progress_before_its_first_block_ends(flow, tmp_path):
    policy, store = flow
    reports = []
    with listening(lambda task, done, total, fields: reports.append((task, done, total, fields))):
        summary = generate_couplings(policy, store, tmp_path / "c.zarr", CouplingConfig(
            samples_per_window=4, solver="rk45", rtol=1e-3, atol=1e-3, max_windows=20,
            batch_windows=10))
    couplings = [r for r in reports if r[0] == "couplings"]
    done = [r[1] for r in couplings]
    assert done == sorted(done) and done[0] == 0 and done[-1] == 20  # never back
    assert summary["n"] == 80
    # the first block (windows 0-9) is written when done reaches 10: before that, the reports
    # move with its solve, each a network evaluation
    first_block = done.index(10)
    inside = couplings[1:first_block]
    assert len(inside) > 10  # an evaluation each (rk45: tens of them)
    assert {r[1] for r in inside} > {0} and max(r[1] for r in inside) <= 9
    assert all(r[3]["couplings"] == 0 for r in inside)  # none written yet
    assert [r[3]["NFE_in_block"] for r in inside] == list(range(1, len(inside) + 1))
