"""Reflow's captured velocity field (sefa_model/flow/cuda_graphs.py: FieldGraphs), on the CPU.

A CUDA graph cannot be recorded without CUDA, so these tests hand FieldGraphs a recorder that
behaves as a replayed graph does (static buffers recorded from the first call's inputs, each
later call copied into them) and check what decides correctness on a GPU: which calls share a
graph (the tag and every input's shape), that a replay computes what the eager field does, that
the shrinking batches of the per-sample solvers are never recorded, and that a failed capture
runs eager with one warning. The CUDA replay itself is tests/test_gpu.py's
`test_reflow_with_the_field_captured_gives_the_eager_couplings`."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

from sefa_model.flow.cuda_graphs import FieldGraphs


class FakeGraph:
    """A recorded call as CapturedCall makes it: buffers cloned from the example inputs, and
    each call copies its inputs into them before running the recorded function on the buffers."""

    recorded: list[tuple] = []

    def __init__(self, fn, *args):
        self.fn, self.args = fn, tuple(a.clone() for a in args)
        FakeGraph.recorded.append(tuple(a.shape for a in args))

    def __call__(self, *args):
        for dst, src in zip(self.args, args):
            dst.copy_(src)
        return self.fn(*self.args).clone()


@pytest.fixture(autouse=True)
def fresh_record():
    FakeGraph.recorded = []


def field(x, t, cond):
    return x * t[:, None, None] + cond[:, None, :2]


def inputs(rows: int, seed: int):
    gen = torch.Generator().manual_seed(seed)
    return torch.randn(rows, 4, 2, generator=gen), torch.rand(rows, generator=gen), \
        torch.randn(rows, 3, generator=gen)


def test_a_graph_per_tag_and_shape_recorded_once_and_replayed_with_each_calls_inputs():
    graphs = FieldGraphs(record=FakeGraph)
    f, g = graphs.field(field), graphs.field(lambda x, t, c: 2 * field(x, t, c), tag=0.5)
    for seed in range(3):
        for rows in (8, 8, 3):
            x, t, c = inputs(rows, seed)
            torch.testing.assert_close(f(x, t, c), field(x, t, c), rtol=0, atol=0)
            torch.testing.assert_close(g(x, t, c), 2 * field(x, t, c), rtol=0, atol=0)
    # (no tag, 8 rows), (0.5, 8), (None, 3), (0.5, 3): four graphs for 18 calls
    assert len(FakeGraph.recorded) == 4 and len(graphs.graphs) == 4
    assert graphs.replays == 18 and graphs.eager == 0


def test_a_failed_capture_runs_eager_and_warns_once():
    def refuse(fn, *args):
        raise RuntimeError("operation not permitted when stream is capturing\nmore")

    graphs = FieldGraphs(record=refuse)
    f = graphs.field(field)
    x, t, c = inputs(5, 0)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = [f(x, t, c) for _ in range(3)]
    assert [str(w.message) for w in caught] == [
        "running the velocity field eager: its CUDA graph capture at (5, 4, 2) failed "
        "(operation not permitted when stream is capturing)"]
    for o in out:
        torch.testing.assert_close(o, field(x, t, c), rtol=0, atol=0)
    assert graphs.eager == 3 and graphs.replays == 0


def flow_model(deploy_workspace):
    from sefa_model.policy.artifact import Policy

    return Policy.load(deploy_workspace / "flow").model


@pytest.mark.parametrize("solver,steps,replayed", [("rk45", None, True), ("euler", 4, True),
                                                   ("rk45-ps", None, False)])
def test_sample_replays_the_field_in_whole_batch_solvers_only(deploy_workspace, solver, steps,
                                                              replayed):
    """rk45 and the fixed-step solvers evaluate every row at every call: one graph, every call
    replayed, the same chunks and NFE as eager. A per-sample solver's batch shrinks as samples
    finish: it is never recorded."""
    model = flow_model(deploy_workspace)
    gen = torch.Generator().manual_seed(0)
    cond = torch.randn(6, model.obs_encoder.out_dim, generator=gen)
    noise = torch.randn(6, model.cfg.policy.horizon, 2, generator=gen)
    graphs = FieldGraphs(record=FakeGraph)
    with torch.no_grad():
        eager = model.sample(cond, noise, solver=solver, steps=steps)
        got = model.sample(cond, noise, solver=solver, steps=steps, graphs=graphs)
    torch.testing.assert_close(got.x, eager.x, rtol=0, atol=0)
    assert got.nfe == eager.nfe
    if replayed:
        assert FakeGraph.recorded == [((6, model.cfg.policy.horizon, 2), (6,), cond.shape)]
        assert graphs.replays == got.nfe and graphs.eager == 0
    else:
        assert FakeGraph.recorded == [] and graphs.replays == graphs.eager == 0


def test_couplings_on_the_cpu_are_solved_eager_and_say_so(deploy_workspace, tmp_path):
    """`capture` is how a solve runs on CUDA, not a setting: on the CPU the couplings are the
    same with it on or off, and their attributes say no graph was used."""
    from sefa_model.data.couplings import read_couplings
    from sefa_model.policy.artifact import Policy
    from sefa_model.sefa.reflow import CouplingConfig, generate_couplings

    policy = Policy.load(deploy_workspace / "flow")
    cfg = CouplingConfig(samples_per_window=2, max_windows=6, batch_windows=4)
    on = generate_couplings(policy, deploy_workspace / "dataset.zarr", tmp_path / "on.zarr", cfg)
    off = generate_couplings(policy, deploy_workspace / "dataset.zarr", tmp_path / "off.zarr",
                             cfg, capture=False)
    assert on["cuda_graphs"] is False and off["cuda_graphs"] is False
    a, b = read_couplings(tmp_path / "on.zarr"), read_couplings(tmp_path / "off.zarr")
    assert a.attrs["cuda_graphs"] is False
    np.testing.assert_array_equal(a.action, b.action)
