"""Offline evaluation on a camera store finds the expert spread's neighbours from the low-dim
observations without reading any training window's images (it read every window's frames
after its progress bar had ended: half a minute of silence on LeRobot's Push-T), and finds
the same neighbours, so the same numbers, as reading them all did. A tiny camera flow trained
on LeRobot's Push-T (5 episodes, a 96x96 camera and the agent's position)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sefa_data.ingest import IngestOptions, ingest
from sefa_data.sampler import SequenceSampler
from sefa_data.store.zarr_store import EpisodeStore
from sefa_model.config import load_train_config
from sefa_model.data.windows import PolicyData
from sefa_model.eval.offline import _flat_obs, evaluate_offline, lowdim_obs, nearest_windows
from sefa_model.policy.artifact import Policy
from sefa_model.train.loop import train

TINY = ["policy.head=mlp", "policy.mlp_hidden_dims=[32,32]", "policy.time_embed_dim=16",
        "policy.image_encoder=tiny", "policy.resize_shape=[32,32]", "training.max_steps=2",
        "training.batch_size=8", "training.val_every=2", "training.checkpoint_every=2",
        "training.val_batches=1", "training.val_sample_windows=4", "flow.solver=euler",
        "flow.steps=2"]


@pytest.fixture(scope="module")
def camera_flow(shared_data, tmp_path_factory) -> tuple[Path, Path]:
    ws = tmp_path_factory.mktemp("camera_offline")
    source = shared_data / "lerobot_pusht5_image_v30"
    if not source.is_dir():
        pytest.skip(f"{source} not found")
    ingest([source], ws / "dataset.zarr", IngestOptions())
    train(load_train_config(None, TINY), ws / "flow", ws / "dataset.zarr")
    return ws / "flow", ws / "dataset.zarr"


def test_the_expert_spread_reads_no_training_images_and_finds_the_same_neighbours(
        camera_flow, monkeypatch):
    flow, store = camera_flow
    read = []
    real = SequenceSampler.batch
    monkeypatch.setattr(SequenceSampler, "batch",
                        lambda self, idx: read.append(len(idx)) or real(self, idx))
    row = evaluate_offline(flow, store, windows=4, samples=3, device="cpu")
    assert read and max(read) <= 4  # the evaluated windows only, never the training set
    assert row["expert_spread"] > 0

    # the neighbours from the low-dim keys alone are those of the full windows' tensors
    policy = Policy.load(flow, device="cpu")
    data = PolicyData(policy.cfg, EpisodeStore.open(store), policy.normalizer)
    everything, _ = data.tensors(data.train, np.arange(len(data.train)), policy.device)
    assert set(everything) == {"observation.image", "observation.state"}
    lowdim = lowdim_obs(data)
    assert set(lowdim) == {"observation.state"}
    np.testing.assert_array_equal(lowdim["observation.state"].numpy(),
                                  everything["observation.state"].numpy())
    query = _flat_obs(policy, {k: v[:5] for k, v in everything.items()})
    np.testing.assert_array_equal(nearest_windows(query, _flat_obs(policy, lowdim), 3),
                                  nearest_windows(query, _flat_obs(policy, everything), 3))


def test_the_progress_of_an_adaptive_solve_never_goes_back(camera_flow):
    """RK45 evaluates stages at earlier times and retries rejected steps: the bar went 8, 7, 6
    of 1000, which the progress display read as a new run (its rate and ETA lost). It keeps
    the furthest time reached, ending at the whole."""
    from sefa_model.progress import listening

    flow, store = camera_flow
    seen = []
    with listening(lambda task, done, total, fields: seen.append((task, done, total))):
        evaluate_offline(flow, store, windows=2, samples=2, solver="rk45", device="cpu")
    bar = [(d, total) for task, d, total in seen if task == "offline eval"]
    done = [d for d, _ in bar]
    assert len(done) > 6 and done == sorted(done) and done[-1] == bar[-1][1]
