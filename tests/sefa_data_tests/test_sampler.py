"""The sequence sampler against Diffusion Policy's semantics, on small stores and on Push-T."""

import hashlib
import os
import pickle
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest
import torch

from sefa_data.episode import Episode
from sefa_data.errors import SefaInputError
from sefa_data.ingest import IngestOptions, ingest
from sefa_data.sampler import SequenceSampler, create_indices, to_torch
from sefa_data.store.zarr_store import EpisodeStore


# --------------------------------------------------------------------------- references


def dp_create_indices(episode_ends, sequence_length, pad_before, pad_after, episode_mask):
    """Diffusion Policy's `create_indices`, transcribed loop for loop (without numba)."""
    pad_before = min(max(pad_before, 0), sequence_length - 1)
    pad_after = min(max(pad_after, 0), sequence_length - 1)
    rows = []
    for i in range(len(episode_ends)):
        if not episode_mask[i]:
            continue
        start_idx = episode_ends[i - 1] if i > 0 else 0
        episode_length = episode_ends[i] - start_idx
        for idx in range(-pad_before, episode_length - sequence_length + pad_after + 1):
            buffer_start = max(idx, 0) + start_idx
            buffer_end = min(idx + sequence_length, episode_length) + start_idx
            start_offset = buffer_start - (idx + start_idx)
            end_offset = (idx + sequence_length + start_idx) - buffer_end
            rows.append([buffer_start, buffer_end, start_offset, sequence_length - end_offset])
    return np.array(rows, dtype=np.int64).reshape(-1, 4)


def dp_sample(buffer: np.ndarray, row, sequence_length: int) -> np.ndarray:
    """Diffusion Policy's `sample_sequence` for one key: slice, then repeat the edge frames."""
    buffer_start, buffer_end, sample_start, sample_end = row
    sample = buffer[buffer_start:buffer_end]
    data = np.zeros((sequence_length,) + buffer.shape[1:], buffer.dtype)
    data[:sample_start] = sample[0]
    data[sample_end:] = sample[-1]
    data[sample_start:sample_end] = sample
    return data


def src(name):
    return {"path": name, "sha256": hashlib.sha256(name.encode()).hexdigest(), "size": 1}


def small_store(path: Path, lengths, zarr_format: int = 2) -> EpisodeStore:
    """Episodes whose every value encodes its global frame index, so windows read plainly."""
    episodes, first = [], 0
    for n in lengths:
        frame = np.arange(first, first + n)
        episodes.append(Episode({
            "action": np.stack([frame, -frame], axis=1).astype(np.float32),
            "state": (frame[:, None, None] * np.ones((1, 3, 2))).astype(np.float32),
            "cam": (frame[:, None, None, None] % 256 * np.ones((1, 8, 10, 3))).astype(np.uint8),
        }, source="t"))
        first += n
    store = EpisodeStore.create(path, fps=10, zarr_format=zarr_format)
    store.append(iter(episodes), src(str(path)))
    return store


@pytest.fixture(scope="module")
def pusht(tmp_path_factory, shared_data):
    """Push-T ingested once. On a RAM disk where there is one: the store is 25,650 image files,
    and on a small VM's disk creating and later deleting them costs over 30 s."""
    shm = Path("/dev/shm")
    ram = shm.is_dir() and os.access(shm, os.W_OK)
    base = Path(tempfile.mkdtemp(dir=shm)) if ram else tmp_path_factory.mktemp("pusht")
    ingest([shared_data / "pusht_cchi_v7_replay.zarr"], base / "p.zarr", IngestOptions(fps=10))
    yield EpisodeStore.open(base / "p.zarr")
    shutil.rmtree(base, ignore_errors=True)


# --------------------------------------------------------------------------- create_indices


def test_create_indices_hand_example():
    # one episode of 3 frames, windows of 3 with one frame of padding each side
    assert create_indices(np.array([3]), 3, 1, 1).tolist() == [
        [0, 2, 1, 3],  # starts one frame early: frame 0 repeated in front
        [0, 3, 0, 3],
        [1, 3, 0, 2],  # ends one frame late: frame 2 repeated at the back
    ]


@pytest.mark.parametrize("seq,pad_before,pad_after", [
    (1, 0, 0), (4, 0, 0), (4, 1, 3), (16, 1, 7), (16, 5, 15), (6, 9, 9), (20, 0, 0)])
def test_create_indices_matches_diffusion_policy(seq, pad_before, pad_after):
    rng = np.random.default_rng(seq + pad_before)
    lengths = rng.integers(1, 30, size=12)
    ends = np.cumsum(lengths)
    mask = rng.random(12) < 0.7
    got = create_indices(ends, seq, pad_before, pad_after, mask)
    assert got.dtype == np.int64 and got.shape[1] == 4
    np.testing.assert_array_equal(got, dp_create_indices(ends, seq, pad_before, pad_after, mask))
    # windows per episode: L + pad_before + pad_after - T + 1 (padding clamped to T - 1), or 0
    pb, pa = min(pad_before, seq - 1), min(pad_after, seq - 1)
    episode = np.searchsorted(ends, got[:, 0], side="right")
    counts = np.bincount(episode, minlength=12)
    np.testing.assert_array_equal(counts, np.maximum(lengths + pb + pa - seq + 1, 0) * mask)
    # real frames never cross an episode end
    assert (got[:, 1] <= ends[episode]).all()


# --------------------------------------------------------------------------- small stores


def test_windows_repeat_first_and_last_frame(tmp_path):
    store = small_store(tmp_path / "s.zarr", [5, 7])  # one episode per split
    for split in ("train", "valid"):
        s = SequenceSampler(store, horizon=4, n_obs_steps=2, n_action_steps=3, split=split,
                            obs_keys=["state", "cam"])
        assert s.pad_before == 1 and s.pad_after == 2
        episode = s.window_index(0).episode
        first = int(store.episode_ends[episode]) - int(store.episode_lengths[episode])
        last = int(store.episode_ends[episode]) - 1
        assert len(s) == store.episode_lengths[episode] + 1 + 2 - 4 + 1  # L + pads - T + 1

        w = s.window(0)  # starts one frame before the episode: its first frame repeated
        assert w["action"][:, 0].tolist() == [first, first, first + 1, first + 2]
        assert w["action"][:, 1].tolist() == [-first, -first, -first - 1, -first - 2]
        assert w["state"][:, 0, 0].tolist() == [first, first]
        assert w["cam"][:, 0, 0, 0].tolist() == [first, first]
        assert w["state"].shape == (2, 3, 2) and w["cam"].shape == (2, 8, 10, 3)
        w = s.window(len(s) - 1)  # ends two frames after the episode: its last frame repeated
        assert w["action"][:, 0].tolist() == [last - 1, last, last, last]
        assert w["state"][:, 0, 0].tolist() == [last - 1, last]
        assert s.window_index(0) == (episode, -1)
        assert s.window_index(len(s) - 1) == (episode, last - first - 1)


@pytest.mark.parametrize("zarr_format", [2, 3])
def test_window_and_batch_equal_dp_reference(tmp_path, zarr_format):
    store = small_store(tmp_path / "s.zarr", [3, 9, 1, 6, 16], zarr_format)
    horizon, n_obs, n_act = 6, 3, 4
    s = SequenceSampler(store, horizon, n_obs, n_act, split="train", obs_keys=["state", "cam"])
    data = {k: store.root["data"][k][:] for k in ("action", "state", "cam")}
    rows = dp_create_indices(store.episode_ends, horizon, n_obs - 1, n_act - 1, store.mask("train"))
    np.testing.assert_array_equal(s.indices, rows)
    for i, row in enumerate(rows):
        w = s.window(i)
        np.testing.assert_array_equal(w["action"], dp_sample(data["action"], row, horizon))
        for key in ("state", "cam"):
            np.testing.assert_array_equal(w[key], dp_sample(data[key], row, horizon)[:n_obs])
    b = s.batch(np.arange(len(s)))
    for key in ("action", "state", "cam"):
        np.testing.assert_array_equal(b[key], np.stack([s.window(i)[key] for i in range(len(s))]))


def test_splits_use_only_their_episodes(tmp_path):
    store = small_store(tmp_path / "s.zarr", [8] * 12)
    for split in ("train", "valid"):
        s = SequenceSampler(store, 4, 2, 2, split=split, obs_keys=["state"])
        used = {s.window_index(i).episode for i in range(len(s))}
        assert used == set(np.flatnonzero(store.mask(split)).tolist())
        assert len(s) == store.mask(split).sum() * (8 + 1 + 1 - 4 + 1)


def test_empty_split_names_store_and_split(tmp_path):
    store = small_store(tmp_path / "one.zarr", [8])  # one episode cannot be split
    with pytest.raises(SefaInputError, match=r"one\.zarr.*'valid' split has no episodes"):
        SequenceSampler(store, 4, 2, 2, split="valid", obs_keys=["state"])
    with pytest.raises(SefaInputError, match="long enough"):
        SequenceSampler(store, 20, 1, 1, obs_keys=["state"])
    with pytest.raises(SefaInputError, match="no such key"):
        SequenceSampler(store, 4, 2, 2, obs_keys=["nope"])


def test_image_cache_stays_bounded(tmp_path):
    store = small_store(tmp_path / "s.zarr", [40, 40, 40])
    s = SequenceSampler(store, 4, 2, 2, obs_keys=["cam"], image_cache_frames=10)
    cache = s._images["cam"]
    rng = np.random.default_rng(0)
    for _ in range(20):
        idx = rng.integers(0, len(s), 16)
        b = s.batch(idx)
        assert len(cache) <= 10
        # still the right frames, though most were evicted on the way
        np.testing.assert_array_equal(b["cam"][:, :, 0, 0, 0], s.frame_indices(idx)[:, :2] % 256)
    uncached = SequenceSampler(store, 4, 2, 2, obs_keys=["cam"], image_cache_frames=0)
    np.testing.assert_array_equal(uncached.batch(np.arange(30))["cam"],
                                  s.batch(np.arange(30))["cam"])
    assert len(uncached._images["cam"]) == 0


def test_cache_hits_on_repeated_frames(tmp_path):
    store = small_store(tmp_path / "s.zarr", [20])
    s = SequenceSampler(store, 4, 2, 2, obs_keys=["cam"], image_cache_frames=100)
    cache = s._images["cam"]
    s.batch(np.array([3]))
    hits, misses = cache.hits, cache.misses
    s.batch(np.array([3]))
    assert cache.misses == misses and cache.hits == hits + 2


def test_sampler_pickles_for_spawned_workers(tmp_path):
    store = small_store(tmp_path / "s.zarr", [20, 20])
    s = SequenceSampler(store, 4, 2, 2, obs_keys=["cam", "state"])
    want = s.batch(np.arange(len(s)))
    copy = pickle.loads(pickle.dumps(s))
    assert len(copy._images["cam"]) == 0  # the cache is not shipped
    for key, value in copy.batch(np.arange(len(s))).items():
        np.testing.assert_array_equal(value, want[key])


# --------------------------------------------------------------------------- Push-T


def test_pusht_batch_equals_stacked_windows(pusht):
    s = SequenceSampler(pusht, 16, 2, 8, obs_keys=["img", "keypoint", "state"])
    n = len(s)
    idx = np.concatenate([[0, 1, n - 1], np.random.default_rng(0).integers(0, n, 61)])
    b = s.batch(idx)
    assert b["img"].dtype == np.uint8 and b["img"].shape == (64, 2, 96, 96, 3)
    assert b["keypoint"].shape == (64, 2, 9, 2) and b["action"].shape == (64, 16, 2)
    for key in ("img", "keypoint", "state", "action"):
        np.testing.assert_array_equal(b[key], np.stack([s.window(i)[key] for i in idx]))
    action = pusht.root["data"]["action"][:]
    for j, i in enumerate(idx[:8]):  # against DP's slice-and-pad on the raw array
        np.testing.assert_array_equal(b["action"][j], dp_sample(action, s.indices[i], 16))


def test_pusht_windows_per_episode_and_no_crossing(pusht):
    s = SequenceSampler(pusht, 16, 2, 8, obs_keys=["state"])
    lengths, train = pusht.episode_lengths, pusht.mask("train")
    assert len(s) == int(((lengths + 1 + 7 - 16 + 1) * train).sum())
    frames = s.frame_indices(np.arange(len(s)))
    episode_of_frame = np.searchsorted(pusht.episode_ends, frames, side="right")
    episodes = np.array([s.window_index(i).episode for i in range(len(s))])
    assert (episode_of_frame == episodes[:, None]).all()
    assert set(episodes.tolist()) == set(np.flatnonzero(train).tolist())
    v = SequenceSampler(pusht, 16, 2, 8, split="valid", obs_keys=["state"])
    v_eps = {v.window_index(i).episode for i in range(len(v))}
    assert v_eps == set(np.flatnonzero(pusht.mask("valid")).tolist()) and not v_eps & set(episodes)


def test_to_torch_shapes_dtypes_range(pusht):
    s = SequenceSampler(pusht, 16, 2, 8, obs_keys=["img", "state"])
    b = s.batch(np.arange(5))
    t = to_torch(b, "cpu", image_keys=s.image_keys)
    assert t["img"].shape == (5, 2, 3, 96, 96) and t["img"].dtype == torch.float32
    assert 0.0 <= t["img"].min() and t["img"].max() <= 1.0
    np.testing.assert_allclose(t["img"].numpy(),
                               b["img"].transpose(0, 1, 4, 2, 3).astype(np.float32) / 255)
    assert t["state"].dtype == torch.float32 and t["state"].shape == (5, 2, 5)
    assert t["action"].shape == (5, 16, 2)
    assert to_torch(b)["img"].shape == (5, 2, 3, 96, 96)  # image keys inferred


def test_window_subset_maps_every_indexed_read(tmp_path):
    """Row i of a window-level split is window `windows[i]` of the whole sampler, for batches,
    action chunks, frame indices and single windows alike (values encode frame indices)."""
    from sefa_data.sampler import WindowSubset, window_split

    store = small_store(tmp_path / "s.zarr", [30])
    s = SequenceSampler(store, horizon=4, n_obs_steps=2, n_action_steps=3, split="train",
                        obs_keys=["state", "cam"])
    tr, va = window_split(len(s), 4)
    assert len(set(s.frame_indices(tr).ravel()) & set(s.frame_indices(va).ravel())) == 0
    sub = WindowSubset(s, va, "valid")
    idx = np.array([0, len(va) - 1])
    np.testing.assert_array_equal(sub.actions(idx), s.actions(va[idx]))
    np.testing.assert_array_equal(sub.actions(idx)[:, :, 0], s.frame_indices(va[idx]))
    np.testing.assert_array_equal(sub.frame_indices(idx), s.frame_indices(va[idx]))
    for key, value in sub.batch(idx).items():
        np.testing.assert_array_equal(value, s.batch(va[idx])[key])
    assert sub.window_index(1) == s.window_index(int(va[1]))
    np.testing.assert_array_equal(sub.window(0)["action"], s.window(int(va[0]))["action"])
