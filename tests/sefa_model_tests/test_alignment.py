"""Selective flow alignment: the metric, the eps rule, the matching-observation search and the
aligned artifact.

Most cases build couplings whose distances are known by construction: the expert chunk is zero
and the generated chunk is c times a unit vector at every step, so mean_t ||.||_2 = c exactly.
One case runs on real Push-T expert chunks.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
import zarr

from sefa_data.errors import SefaInputError
from sefa_model.sefa import alignment
from sefa_model.sefa.alignment import (
    align, distance_histogram, eps_for_fraction, format_histogram, matching_obs_candidates,
    select_targets, select_targets_matching_obs)
from sefa_model.data.couplings import METRIC, chunk_distance

T, DA = 4, 3


def offsets(c, seed: int = 0) -> np.ndarray:
    """(M, T, DA) chunks whose every step is a random unit vector times c[m]: distance to zero
    is exactly c[m], whatever the directions."""
    u = np.random.default_rng(seed).normal(size=(len(c), T, DA))
    u /= np.linalg.norm(u, axis=-1, keepdims=True)
    return (np.asarray(c, np.float64)[:, None, None] * u).astype(np.float32)


def write_couplings(path: Path, noise, action, window, **attrs) -> Path:
    root = zarr.open_group(str(path), mode="w", zarr_format=2)
    root.create_array("noise", data=np.asarray(noise))
    root.create_array("action", data=np.asarray(action))
    root.create_array("window", data=np.asarray(window))
    root.update_attributes({"samples_per_window": 2, "solver": "rk45", **attrs})
    return path


@pytest.fixture
def known(tmp_path):
    """Three windows, two samples each; expert chunks zero; distances C exactly."""
    c = np.array([0.05, 0.2, 0.0, 0.8, 0.1, 0.3])
    window = np.array([0, 0, 1, 1, 2, 2])
    expert = np.zeros((3, T, DA), np.float32)
    action = offsets(c)
    noise = np.random.default_rng(1).normal(size=action.shape).astype(np.float32)
    path = write_couplings(tmp_path / "c.zarr", noise, action, window)
    return path, c, window, expert, action, noise


# --------------------------------------------------------------------------- the metric


def test_distance_is_mean_over_steps_of_l2():
    # two steps: one off by (3, 4), one exact. Mean per-step L2 = 2.5; overall L2 = 5;
    # mean squared error = 25 / 4 = 6.25; RMS over steps = sqrt(12.5)
    gen = np.array([[[3.0, 4.0], [0.0, 0.0]]], np.float32)
    exp = np.zeros_like(gen)
    assert chunk_distance(gen, exp).tolist() == [2.5]
    assert chunk_distance(gen, exp).dtype == np.float32


def test_distance_known_offsets():
    c = np.array([0.0, 0.125, 1.5, 3.0])
    assert np.allclose(chunk_distance(offsets(c), np.zeros((4, T, DA))), c, atol=1e-6)


def test_distance_shape_mismatch():
    with pytest.raises(ValueError):
        chunk_distance(np.zeros((2, T, DA)), np.zeros((2, T, DA + 1)))


# --------------------------------------------------------------------------- the eps rule


def test_select_targets_exact_set(known):
    _, c, window, expert, action, _ = known
    target, replaced, distance = select_targets(action, expert[window], eps=0.15)
    assert replaced.tolist() == [True, False, True, False, True, False]
    assert np.allclose(distance, c, atol=1e-6)
    assert np.array_equal(target[replaced], expert[window][replaced])
    assert np.array_equal(target[~replaced], action[~replaced])
    assert target.dtype == np.float32


def test_eps_is_strict(known):
    _, _, window, expert, action, _ = known
    # c = 0 is not < 0: eps = 0 replaces nothing, even a chunk equal to the expert's
    _, replaced, _ = select_targets(action, expert[window], eps=0.0)
    assert not replaced.any()
    gen = np.full((1, T, DA), 0.0, np.float32)
    gen[0, :, 0] = 0.5
    assert not select_targets(gen, np.zeros_like(gen), eps=0.5)[1].any()
    assert select_targets(gen, np.zeros_like(gen), eps=0.5000001)[1].all()


@pytest.mark.parametrize("eps", [1e6, np.inf])
def test_huge_eps_replaces_everything(known, eps):
    _, _, window, expert, action, _ = known
    target, replaced, _ = select_targets(action, expert[window], eps=eps)
    assert replaced.all() and np.array_equal(target, expert[window])


@pytest.mark.parametrize("eps", [-0.1, np.nan])
def test_bad_eps(known, eps):
    _, _, window, expert, action, _ = known
    with pytest.raises(ValueError):
        select_targets(action, expert[window], eps=eps)


# --------------------------------------------------------------------------- matching observations


def test_candidates_by_max_abs_difference():
    f = np.array([[0.0, 0.0], [0.0, 0.0005], [0.0, 0.002], [1.0, 0.0], [1.0, 0.0]])
    cand = matching_obs_candidates(f, tol=1e-3)
    assert [cand.of(i).tolist() for i in range(5)] == [[0, 1], [0, 1], [2], [3, 4], [3, 4]]
    # tol = 0: exact duplicates only; tol is on the max-abs difference, not the L2 norm
    assert [matching_obs_candidates(f, 0.0).of(i).tolist() for i in range(5)] == \
        [[0], [1], [2], [3, 4], [3, 4]]
    g = np.array([[0.0, 0.0], [0.0009, 0.0009]])  # L2 1.27e-3 > tol, max-abs 9e-4 <= tol
    assert matching_obs_candidates(g, 1e-3).of(0).tolist() == [0, 1]


def test_candidates_match_brute_force_in_blocks():
    rng = np.random.default_rng(3)
    # a coarse grid, so that many windows share some coordinates and a few all of them
    f = rng.integers(0, 4, size=(400, 3)).astype(np.float64) * 0.01
    f += rng.uniform(-1e-4, 1e-4, size=f.shape)
    for tol in (0.0, 1e-3, 0.015):
        cand = matching_obs_candidates(f, tol, block_elems=100)  # many small blocks
        dense = np.abs(f[:, None] - f[None]).max(-1) <= tol
        assert all(cand.of(i).tolist() == np.flatnonzero(dense[i]).tolist() for i in range(400))


def test_candidates_refuse_a_quadratic_blowup():
    with pytest.raises(SefaInputError, match="lower tol"):
        matching_obs_candidates(np.zeros((100, 2)), 1e-3, max_pairs=1000)


def test_matching_obs_finds_a_nearer_chunk_of_another_window():
    # windows 0 and 1 show the same observation, 2 another one; the generated chunk of window 0
    # is 0.3 from its own expert chunk, 0.05 from window 1's and exactly on window 2's
    expert = np.zeros((3, T, DA), np.float32)
    expert[1, :, 0] = 0.25
    expert[2, :, 0] = 0.30
    gen = np.zeros((2, T, DA), np.float32)
    gen[:, :, 0] = 0.30
    window = np.array([0, 2])
    obs = np.array([[1.0, 2.0], [1.0, 2.0], [5.0, 5.0]])
    target, replaced, distance, nearest = select_targets_matching_obs(
        gen, window, expert, obs, eps=0.1, tol=1e-3)
    assert nearest.tolist() == [1, 2]
    assert np.allclose(distance, [0.05, 0.0], atol=1e-6)
    assert replaced.tolist() == [True, True]
    assert np.array_equal(target, expert[[1, 2]])
    # same_window would keep coupling 0 (0.3 >= eps)
    assert select_targets(gen, expert[window], 0.1)[1].tolist() == [False, True]
    # window 2's chunk is nearer but its observation differs: not a candidate of window 0
    obs_apart = obs.copy()
    obs_apart[1] = [1.0, 2.1]
    _, replaced, distance, nearest = select_targets_matching_obs(
        gen[:1], window[:1], expert, obs_apart, eps=0.1, tol=1e-3)
    assert nearest.tolist() == [0] and not replaced[0]
    assert np.allclose(distance, [0.3], atol=1e-6)


def test_matching_obs_prefers_own_window_on_ties_and_blocks_agree():
    rng = np.random.default_rng(5)
    expert = np.repeat(rng.normal(size=(1, T, DA)), 6, axis=0).astype(np.float32)  # all equal
    obs = np.zeros((6, 2))
    window = np.repeat(np.arange(6), 3)
    gen = (expert[window] + 0.01 * rng.normal(size=(18, T, DA))).astype(np.float32)
    out = select_targets_matching_obs(gen, window, expert, obs, eps=1.0, tol=0.0)
    assert out[3].tolist() == window.tolist()
    small = select_targets_matching_obs(gen, window, expert, obs, eps=1.0, tol=0.0, block_elems=1)
    assert all(np.array_equal(a, b) for a, b in zip(out, small))


# --------------------------------------------------------------------------- histogram


def test_histogram():
    h = distance_histogram(np.array([0.0, 0.5, 1.0, 2.0]), bins=4)
    assert h == {"edges": [0.0, 0.5, 1.0, 1.5, 2.0], "counts": [1, 1, 1, 1]}
    assert distance_histogram(np.zeros(3), bins=2) == {"edges": [0.0, 0.5, 1.0], "counts": [3, 0]}
    text = format_histogram(h, width=10, eps=0.7)
    lines = text.splitlines()
    assert len(lines) == 4 and lines[0].count("#") == 10 and "eps=0.7" in lines[1]


# --------------------------------------------------------------------------- the artifact


def test_align_round_trip(known, tmp_path):
    path, c, window, expert, action, noise = known
    out = tmp_path / "aligned.zarr"
    summary = align(path, expert, out, eps=0.15)

    root = zarr.open_group(str(out), mode="r")
    assert root.metadata.zarr_format == 2
    assert sorted(root.array_keys()) == ["distance", "noise", "replaced", "target", "window"]
    replaced = np.array([True, False, True, False, True, False])
    assert np.array_equal(root["noise"][:], noise)
    assert np.array_equal(root["window"][:], window) and root["window"].dtype == np.int64
    assert np.array_equal(root["replaced"][:], replaced) and root["replaced"].dtype == bool
    assert np.allclose(root["distance"][:], c, atol=1e-6)
    assert root["distance"].dtype == np.float32 and root["target"].dtype == np.float32
    target = root["target"][:]
    assert np.array_equal(target[replaced], expert[window][replaced])
    assert np.array_equal(target[~replaced], action[~replaced])

    attrs = dict(root.attrs)
    assert attrs["eps"] == 0.15 and attrs["metric"] == METRIC and attrs["n"] == 6
    assert attrs["variant"] == "same_window" and attrs["fraction_replaced"] == 0.5
    assert attrs["histogram"] == distance_histogram(root["distance"][:])
    assert attrs["couplings_attrs"]["samples_per_window"] == 2
    assert summary["fraction_replaced"] == 0.5 and summary["n"] == 6
    assert summary["histogram"] == attrs["histogram"]
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []

    # running again with another eps replaces the artifact whole
    align(path, expert, out, eps=0.0)
    assert zarr.open_group(str(out), mode="r").attrs["fraction_replaced"] == 0.0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["aligned.zarr", "c.zarr"]


def test_align_matching_obs_variant(known, tmp_path):
    path, c, window, expert, action, _ = known
    expert = expert.copy()
    # windows 1 and 2 share an observation, window 0 has its own. Window 2's expert chunk is
    # now coupling 3's generated one (window 1): coupling 3 snaps to it, and coupling 4
    # (window 2, 0.1 from zero) snaps to window 1's zero chunk instead of its own
    expert[2] = action[3]
    obs = np.array([[0.0], [1.0], [1.0]])
    summary = align(path, expert, tmp_path / "a.zarr", eps=0.15, variant="matching_obs",
                    obs_features=obs)
    root = zarr.open_group(str(tmp_path / "a.zarr"), mode="r")
    assert root["replaced"][:].tolist() == [True, False, True, True, True, False]
    assert np.allclose(root["distance"][:], [0.05, 0.2, 0.0, 0.0, 0.1, 0.3], atol=1e-6)
    assert np.array_equal(root["target"][3], action[3])
    assert np.array_equal(root["target"][4], expert[1])
    assert summary["replaced_from_other_window"] == 2 and root.attrs["variant"] == "matching_obs"
    assert root.attrs["tol"] == 1e-3


def _fail(*args, **kwargs):
    raise OSError("disk full")


@pytest.mark.parametrize("where", ["create_array", "os.replace"])
def test_align_is_atomic(known, tmp_path, monkeypatch, where):
    path, _, _, expert, _, _ = known
    out = tmp_path / "aligned.zarr"
    if where == "os.replace":
        monkeypatch.setattr(os, "replace", _fail)
    else:
        real = zarr.Group.create_array
        calls = []

        def third_fails(self, *a, **k):
            calls.append(1)
            if len(calls) == 3:
                raise OSError("disk full")
            return real(self, *a, **k)
        monkeypatch.setattr(zarr.Group, "create_array", third_fails)
    with pytest.raises(OSError, match="disk full"):
        align(path, expert, out, eps=0.15)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.zarr"]


def test_failed_rerun_keeps_the_old_artifact(known, tmp_path, monkeypatch):
    path, _, _, expert, _, _ = known
    out = tmp_path / "aligned.zarr"
    align(path, expert, out, eps=0.15)
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    real = os.replace

    def second_fails(src, dst):  # the old artifact has been moved aside when the swap fails
        if Path(src).name.startswith(".aligned.zarr.tmp"):
            raise OSError("disk full")
        return real(src, dst)
    monkeypatch.setattr(os, "replace", second_fails)
    with pytest.raises(OSError):
        align(path, expert, out, eps=0.5)
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["aligned.zarr", "c.zarr"]


# --------------------------------------------------------------------------- bad input


def test_bad_inputs(known, tmp_path):
    path, _, window, expert, action, noise = known
    out = tmp_path / "a.zarr"
    cases = [
        (dict(couplings_path=tmp_path / "none.zarr"), "no such couplings"),
        (dict(eps=-1.0), "eps"),
        (dict(variant="nearest"), "unknown variant"),
        (dict(expert_chunks=expert[:2]), "window index 2 outside the 2"),
        (dict(expert_chunks=np.zeros((3, T + 1, DA))), "expert chunks have shape"),
        (dict(variant="matching_obs"), "needs obs_features"),
        (dict(variant="matching_obs", obs_features=np.zeros((2, 1))), "obs_features"),
        (dict(out_path=path), "overwrite the couplings"),
    ]
    for override, message in cases:
        args = dict(couplings_path=path, expert_chunks=expert, out_path=out, eps=0.1)
        with pytest.raises(SefaInputError, match=message):
            align(**{**args, **override})
    assert not out.exists()

    bad = [("action", dict(noise=noise[:, :2]), "differs from noise"),
           ("window", dict(window=window - 1), "window index -1"),
           ("window", dict(window=window.astype(np.float32)), "integer"),
           ("action", dict(action=np.where(action == action[3, 1, 2], np.nan, action)), "NaN")]
    for i, (key, override, message) in enumerate(bad):
        arrays = {**dict(noise=noise, action=action, window=window), **override}
        p = write_couplings(tmp_path / f"bad{i}.zarr", **arrays)
        with pytest.raises(SefaInputError, match=message) as e:
            align(p, expert, out, eps=0.1)
        assert f"{p}: {key}: " in str(e.value)  # names the file and the array

    root = zarr.open_group(str(tmp_path / "missing.zarr"), mode="w", zarr_format=2)
    root.create_array("noise", data=noise)
    with pytest.raises(SefaInputError, match="action: no array"):
        align(tmp_path / "missing.zarr", expert, out, eps=0.1)

    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "keep.txt").write_text("x")
    with pytest.raises(SefaInputError, match="not an aligned artifact"):
        align(path, expert, tmp_path / "other", eps=0.1)
    assert (tmp_path / "other" / "keep.txt").exists()


# --------------------------------------------------------------------------- real data


def test_real_pusht_chunks(shared_data, tmp_path):
    from sefa_data.ingest import IngestOptions, ingest
    from sefa_data.normalizer import Normalizer, train_frames
    from sefa_data.sampler import SequenceSampler
    from sefa_data.store.zarr_store import EpisodeStore

    ingest([shared_data / "pusht_cchi_v7_replay.zarr"], tmp_path / "p.zarr",
           IngestOptions(fps=10, keys=["keypoint", "state", "action"]))
    store = EpisodeStore.open(tmp_path / "p.zarr")
    sampler = SequenceSampler(store, 16, 2, 8, obs_keys=["keypoint", "state"])
    modes = {"action": "limits", "keypoint": "limits", "state": "limits"}
    norm = Normalizer.fit({k: train_frames(store, k) for k in modes}, modes)
    batch = sampler.batch(np.arange(len(sampler)))
    expert = norm.normalize("action", batch["action"]).astype(np.float32)
    n = len(expert)

    # two samples per window: sample 0 = the expert chunk of another window (a real, wrong
    # chunk), sample 1 = the expert chunk plus noise of about 0.006 mean per-step L2
    rng = np.random.default_rng(0)
    other = (np.arange(n) + rng.integers(1, n, size=n)) % n  # never the window itself
    window = np.repeat(np.arange(n), 2)
    wrong = np.arange(len(window)) % 2 == 0
    action = expert[window].copy()
    action[wrong] = expert[other]
    action[~wrong] += (0.005 * rng.normal(size=action[~wrong].shape)).astype(np.float32)
    path = write_couplings(tmp_path / "c.zarr", rng.normal(size=action.shape).astype(np.float32),
                           action, window)

    eps = 0.05
    summary = align(path, expert, tmp_path / "a.zarr", eps=eps)
    replaced = zarr.open_group(str(tmp_path / "a.zarr"), mode="r")["replaced"][:]
    # every noisy sample is replaced; a wrong chunk only where it happens to lie within eps of
    # the right one, judged by an independent formula of the metric
    by_chance = np.sqrt(((action - expert[window]) ** 2).sum(-1)).mean(-1) < eps
    assert replaced[~wrong].all()
    assert np.array_equal(replaced[wrong], by_chance[wrong])
    assert by_chance[wrong].mean() < 0.01
    assert summary["fraction_replaced"] == pytest.approx(0.5 + by_chance[wrong].sum() / len(window))
    assert summary["n"] == 2 * n
    print("\n" + format_histogram(summary["histogram"], eps=eps))

    # matching_obs on the real observations: Push-T has no two identical observations, so a
    # tiny tol matches each window only to itself; a loose tol can only add replacements
    obs = np.concatenate([norm.normalize(k, batch[k]).reshape(n, -1)
                          for k in ("keypoint", "state")], axis=1)
    tight = select_targets_matching_obs(action, window, expert, obs, eps, tol=1e-6)
    assert np.array_equal(tight[1], replaced) and np.array_equal(tight[3], window)
    loose = select_targets_matching_obs(action, window, expert, obs, eps, tol=0.05)
    assert (loose[1] >= replaced).all() and (loose[2] <= tight[2]).all()


def test_eps_auto_on_couplings_far_from_the_expert_refuses_and_a_fixed_eps_warns(shared_data,
                                                                                tmp_path):
    """Real Push-T action chunks (normalized to [-1, 1]) as the expert; a base flow whose every
    sample is 3 normalized units from its window's expert chunk, farther than the mean action
    chunk is: --eps auto (replace_fraction 0.2) stops in one line and writes nothing (it went
    ahead while its own warning said the base flow was untrained); the same eps given as a
    number aligns, and the report says why that is no alignment. Samples 0.01 away (a trained
    flow's near misses) align by the fraction and say nothing."""
    from sefa_pipelines.report import distance_quantiles, eps_warning
    from sefa_model.sefa.alignment import mean_action_distance

    src = zarr.open_group(str(shared_data / "pusht_cchi_v7_replay.zarr"), mode="r")
    actions = src["data"]["action"][:400].astype(np.float64)
    lo, hi = actions.min(axis=0), actions.max(axis=0)
    normalized = 2 * (actions - lo) / (hi - lo) - 1
    expert = np.stack([normalized[i:i + 16] for i in range(0, 384, 8)]).astype(np.float32)
    window = np.repeat(np.arange(len(expert)), 2)
    spread = mean_action_distance(expert)
    assert 0.1 < spread < 1.5
    for offset, warned in ((3.0, True), (0.01, False)):
        rng = np.random.default_rng(3)
        angle = rng.uniform(0, 2 * np.pi, size=(len(window), 16))
        off = offset * rng.uniform(0.8, 1.2, size=len(window))  # 2.4 to 3.6 (or 0.008 to 0.012)
        step = off[:, None, None] * np.stack([np.cos(angle), np.sin(angle)], axis=-1)
        action = (expert[window] + step).astype(np.float32)
        path = write_couplings(tmp_path / f"c{offset}.zarr", np.zeros_like(action), action, window)
        out = tmp_path / f"a{offset}.zarr"
        if warned:
            with pytest.raises(SefaInputError) as e:
                align(path, expert, out, eps=0.1, replace_fraction=0.2)
            assert e.value.key == "replace_fraction" and not out.exists()
            assert "the nearest 20% of the couplings lie up to " in e.value.line()
            assert (f"farther than always predicting the mean action ({spread:.3g}, the median): "
                    "the base flow is not trained enough") in e.value.line()
            assert e.value.line().endswith("or align at a fixed eps anyway (--eps E)")
            summary = align(path, expert, out, eps=eps_for_fraction(off, 0.2))  # a number
        else:
            summary = align(path, expert, out, eps=0.1, replace_fraction=0.2)
        assert summary["fraction_replaced"] == pytest.approx(0.2, abs=0.02)
        assert summary["mean_action_distance"] == pytest.approx(spread)
        np.testing.assert_allclose(zarr.open_group(str(out), mode="r")["distance"][:], off,
                                   rtol=1e-5)
        q = distance_quantiles(zarr.open_group(str(out), mode="r")["distance"][:])
        line = eps_warning(summary["fraction_replaced"], summary["eps"], q, spread)
        if warned:
            assert line.startswith(f"warning: eps {summary['eps']:g} replaces chunks up to "), line
            assert f"farther than always predicting the mean action is (median {spread:.3g})" in line
            assert "the base flow is not trained enough" in line
        else:
            assert line is None
