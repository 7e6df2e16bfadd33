"""The stage graph (pipelines/stages.py) is the one description of a workspace's stages: the
stage list, each command's upstream stages and `sefa eval`'s default checkpoints follow from it.
No training here: the graph is pure, and the eval defaults only look for checkpoint folders."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from sefa_pipelines.evals import default_checkpoints
from sefa_pipelines.stages import (CHECKPOINT, PipelineConfig, coupling_source, eval_defaults, needed,
                              stage_graph)


def pipeline(iters: int = 2, align: bool = True) -> PipelineConfig:
    cfg = PipelineConfig()
    cfg.reflow.iters, cfg.distill.align = iters, align
    return cfg


def test_graph_order_artifacts_and_inputs():
    graph = stage_graph(pipeline(iters=3))
    assert [s.name for s in graph] == ["train", "reflow iter 1", "reflow iter 2", "reflow iter 3",
                                       "align", "distill"]
    assert [s.inputs for s in graph] == [(), ("train",), ("reflow/iter_1",), ("reflow/iter_2",),
                                         ("reflow/iter_3",), ("reflow/iter_3", "align")]
    assert [s.policy_dir for s in graph] == ["train", None, "reflow/iter_2/flow",
                                             "reflow/iter_3/flow", None, "distill"]
    # round 1 samples the base flow; later rounds sample their own reflowed flow
    assert coupling_source(graph, "reflow/iter_1") == "train"
    assert coupling_source(graph, "reflow/iter_3") == "reflow/iter_3/flow"


@pytest.mark.parametrize("command, align, families", [
    ("train", True, ["train"]),
    ("reflow", True, ["train", "reflow", "reflow"]),
    ("align", True, ["train", "reflow", "reflow", "align"]),
    ("distill", True, ["train", "reflow", "reflow", "align", "distill"]),
    ("distill", False, ["train", "reflow", "reflow", "distill"]),  # the plain reflow baseline
])
def test_a_commands_stages_are_its_own_and_everything_they_read(command, align, families):
    assert [s.command for s in needed(stage_graph(pipeline(2, align)), command)] == families


def _checkpoints(ws: Path, *policies: str) -> None:
    for p in policies:
        (ws / p / CHECKPOINT).mkdir(parents=True)


def test_eval_defaults_to_the_last_reflow_round_of_the_graph(tmp_path):
    """reflow.iters 3 in sefa.yaml: `sefa eval` evaluates round 3's flow, not round 2's."""
    ws = tmp_path / "ws"
    _checkpoints(ws, "train", "reflow/iter_2/flow", "reflow/iter_3/flow", "distill")
    (ws / "sefa.yaml").write_text(yaml.safe_dump({"reflow": {"iters": 3}}))
    assert default_checkpoints(ws) == [ws / "train", ws / "reflow/iter_3/flow", ws / "distill"]
    # a round not run yet: the last round's flow that exists
    _checkpoints(tmp_path / "two", "train", "reflow/iter_2/flow")
    assert eval_defaults(stage_graph(pipeline(iters=3)), tmp_path / "two") == [
        tmp_path / "two" / "train", tmp_path / "two" / "reflow/iter_2/flow"]
    # one round: no reflowed flow to evaluate
    assert eval_defaults(stage_graph(pipeline(iters=1)), ws) == [ws / "train", ws / "distill"]
