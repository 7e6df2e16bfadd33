"""The episode store's mechanics on small constructed episodes: layout, transactions, stats, masks."""

import hashlib
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import zarr

from sefa_data.episode import Episode
from sefa_data.errors import SefaInputError
from sefa_data.stats import lowdim_stats, stats_from_histogram, image_histogram
from sefa_data.store.zarr_store import IMAGE_STATS_STRIDE, JOURNAL, EpisodeStore, split_masks

REPO = Path(__file__).resolve().parents[2]


def episodes(lengths, seed=0, source="demo.bag"):
    rng = np.random.default_rng(seed)
    return [Episode({"action": rng.normal(size=(n, 2)).astype(np.float32),
                     "observation.images.cam": rng.integers(0, 256, (n, 12, 16, 3), dtype=np.uint8)},
                    source=source, start_time_ns=1000 * i) for i, n in enumerate(lengths)]


def src(name):
    return {"path": name, "sha256": hashlib.sha256(name.encode()).hexdigest(), "size": 1}


def snapshot(path: Path) -> dict[str, bytes]:
    return {str(p.relative_to(path)): p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file()}


@pytest.fixture
def store(tmp_path):
    s = EpisodeStore.create(tmp_path / "s.zarr", fps=10)
    s.append(iter(episodes([5, 7, 9])), src("a"))
    return s


def test_layout_is_diffusion_policy_replay_buffer(store):
    root = zarr.open_group(str(store.path), mode="r")
    assert root.metadata.zarr_format == 2
    ends = root["meta/episode_ends"][:]
    assert ends.dtype == np.int64 and ends.tolist() == [5, 12, 21]
    for key in ("action", "observation.images.cam"):
        assert root["data"][key].shape[0] == ends[-1]
    img = root["data/observation.images.cam"]
    assert img.dtype == np.uint8 and img.chunks == (1, 12, 16, 3)
    assert root["data/action"].chunks[1:] == (2,)
    expected = np.concatenate([e.data["action"] for e in episodes([5, 7, 9])])
    np.testing.assert_array_equal(root["data/action"][:], expected)
    assert root.attrs["fps"] == 10 and root.attrs["sefa_format"] == 1
    assert root.attrs["features"]["observation.images.cam"]["type"] == "image"
    assert (store.path / "data" / "action" / ".zarray").exists()  # format 2 on disk


def test_meta_holds_only_arrays_and_masks_sit_beside_it(store):
    """Diffusion Policy's copy_from_path at commit 27395b7 (2023) reads every member of meta/
    as an array (`len(value.shape)`), so a group there fails it; 5ba07ac (2024) skips groups.
    scripts/dp_replay_check.py runs both commits' own code on a store (docs/results/lerobot.md)."""
    root = zarr.open_group(str(store.path), mode="r")
    assert not list(root["meta"].groups())
    assert set(root["meta"].array_keys()) == {"episode_ends", "episode_source",
                                              "episode_start_time_ns"}
    assert sorted(root["mask"].array_keys()) == ["train", "valid"]
    assert root["mask/train"][:].tolist() == store.mask("train").tolist()
    assert (root["mask/train"][:] | root["mask/valid"][:]).all()


def test_a_mask_of_another_length_is_damage(store):
    (store.path / ".sefa-checksums.json").unlink()  # so the length check, not a checksum, speaks
    zarr.open_group(str(store.path), mode="r+")["mask/train"].resize((2,))
    with pytest.raises(SefaInputError) as e:
        EpisodeStore.open(store.path)
    assert e.value.key == "mask/train" and "2 entries for 3 episodes" in e.value.what


def test_a_store_written_with_meta_mask_still_opens_and_appends(store, tmp_path):
    """Stores written before the masks left meta/ (the old layout, rebuilt here by moving the
    group and its checksum entries) are read and appended to as they are."""
    import json
    import shutil

    old = tmp_path / "old.zarr"
    shutil.copytree(store.path, old)
    (old / "mask").rename(old / "meta" / "mask")
    manifest = json.loads((old / ".sefa-checksums.json").read_text())
    manifest["files"] = {("meta/" + k if k.startswith("mask/") else k): v
                         for k, v in manifest["files"].items()}
    (old / ".sefa-checksums.json").write_text(json.dumps(manifest))
    reopened = EpisodeStore.open(old, verify="full")
    assert reopened.mask_names() == ["train", "valid"]
    assert reopened.mask("train").tolist() == store.mask("train").tolist()
    reopened.append(iter(episodes([4])), src("more"))
    again = EpisodeStore.open(old, verify="full")
    assert len(again.mask("train")) == store.n_episodes + 1 and not (old / "mask").exists()


def test_format_3_on_request(tmp_path):
    s = EpisodeStore.create(tmp_path / "s3.zarr", fps=10, zarr_format=3)
    s.append(iter(episodes([4, 4])), src("a"))
    s.append(iter(episodes([3], seed=1)), src("b"))
    root = zarr.open_group(str(s.path), mode="r")
    assert root.metadata.zarr_format == 3
    assert root["meta/episode_ends"][:].tolist() == [4, 8, 11]


def test_masks_are_seeded_with_one_episode_in_each_split(store):
    train, valid = store.mask("train"), store.mask("valid")
    assert train.sum() >= 1 and valid.sum() >= 1 and not (train & valid).any()
    assert (train | valid).all()
    t2, v2 = split_masks(3, 0.1, 42)
    np.testing.assert_array_equal(t2, train)
    assert split_masks(1, 0.1, 42)[1].sum() == 0  # one episode cannot be split


def test_source_filters_become_masks(tmp_path):
    eps = episodes([3, 3, 3])
    eps[1].filters = {"expert"}
    s = EpisodeStore.create(tmp_path / "f.zarr", fps=10)
    s.append(iter(eps), src("a"))
    assert s.mask("expert").tolist() == [False, True, False]
    s.append(iter(episodes([2], seed=3)), src("b"))
    assert s.mask("expert").tolist() == [False, True, False, False]


def test_stats_match_numpy(store):
    eps = episodes([5, 7, 9])
    stats = store.attrs["stats"]
    act = np.concatenate([e.data["action"] for e in eps]).astype(np.float64)
    np.testing.assert_allclose(stats["action"]["mean"], act.mean(0), rtol=1e-6)
    np.testing.assert_allclose(stats["action"]["q99"], np.quantile(act, 0.99, axis=0), rtol=1e-6)
    img = np.concatenate([e.data["observation.images.cam"] for e in eps])
    img = img[:, ::IMAGE_STATS_STRIDE, ::IMAGE_STATS_STRIDE].reshape(-1, 3)  # the documented subsample
    np.testing.assert_allclose(stats["observation.images.cam"]["mean"], img.mean(0))
    np.testing.assert_allclose(stats["observation.images.cam"]["std"], img.std(0))
    np.testing.assert_array_equal(stats["observation.images.cam"]["q01"],
                                  np.quantile(img, 0.01, axis=0, method="lower"))
    assert stats["observation.images.cam"]["max"] == img.max(0).tolist()


def test_constant_dimensions_are_flagged():
    s = lowdim_stats(np.stack([np.arange(5.0), np.full(5, 3.0)], axis=1))
    assert s.constant.tolist() == [False, True]
    h = image_histogram(np.full((2, 4, 4, 3), 7, np.uint8))
    assert stats_from_histogram(h).constant.tolist() == [True] * 3


def test_reingesting_same_source_is_skipped(store):
    before = snapshot(store.path)
    result = store.append(iter(episodes([2])), src("a"))
    assert result.skipped and snapshot(store.path) == before


@pytest.mark.parametrize("failure", [KeyboardInterrupt, SefaInputError])
def test_failed_append_leaves_store_byte_identical(store, failure):
    before = snapshot(store.path)

    def broken():
        yield from episodes([6, 300], seed=5)  # enough frames to touch the partial last chunk
        raise failure("bad frame") if failure is SefaInputError else failure()

    with pytest.raises(failure):
        store.append(broken(), src("b"))
    assert snapshot(store.path) == before
    assert store.append(iter(episodes([2], seed=6)), src("b")).episodes == 1


def test_new_store_appears_only_after_its_first_commit(tmp_path):
    path = tmp_path / "new.zarr"
    s = EpisodeStore.create(path, fps=10)

    def broken():
        yield episodes([3])[0]
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        s.append(broken(), src("a"))
    assert not path.exists()
    s.discard_if_uncommitted()
    assert list(tmp_path.iterdir()) == []


def test_episode_that_does_not_fit_the_store_is_rejected(store):
    bad = episodes([4])[0]
    bad.data["action"] = bad.data["action"][:, :1]
    before = snapshot(store.path)
    with pytest.raises(SefaInputError, match=r"demo.bag: action: shape \(1,\) float32 where the store has \(2,\) float32"):
        store.append(iter([bad]), src("c"))
    nan = episodes([4])[0]
    nan.data["action"][2, 1] = np.nan
    with pytest.raises(SefaInputError, match=r"action: NaN or Inf value \(at episode 0, frame 2\)"):
        store.append(iter([nan]), src("d"))
    extra = episodes([4])[0]
    extra.data["other"] = extra.data["action"]
    with pytest.raises(SefaInputError, match="other: key not in the store"):
        store.append(iter([extra]), src("e"))
    assert snapshot(store.path) == before


def test_hard_kill_mid_append_is_rolled_back_on_next_open(store):
    """A process killed with os._exit while writing leaves a journal; the next open undoes it.
    (tests/sefa_data_tests/test_store_faults.py kills at every named point of the protocol.)"""
    before = snapshot(store.path)
    code = textwrap.dedent(f"""
        import os, numpy as np
        from sefa_data.store.zarr_store import EpisodeStore
        from sefa_data.episode import Episode
        s = EpisodeStore.open({str(store.path)!r}, mode="a")
        def eps():
            for n in (40, 3):
                yield Episode({{"action": np.ones((n, 2), np.float32),
                               "observation.images.cam": np.ones((n, 12, 16, 3), np.uint8)}}, "x")
        import sefa_data.store.zarr_store as zs
        zs._IMAGE_BATCH_BYTES = 1  # write each episode at once, so the kill lands after real writes
        def dying():
            yield from eps()
            import time; time.sleep(0.5)
            os._exit(9)
        s.append(dying(), {{"path": "x", "sha256": "f" * 64, "size": 1}})
    """)
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO)
    assert proc.returncode == 9
    assert (store.path / JOURNAL).exists() and snapshot(store.path) != before
    # any open rolls back once no live process holds the store's write lock
    assert EpisodeStore.open(store.path).n_episodes == 3
    assert snapshot(store.path) == before
    EpisodeStore.open(store.path, mode="a")
    assert snapshot(store.path) == before


# ---------------------------------------------------------------------------- integrity (issue 12)


def test_every_chunk_is_written_even_all_zeros_and_listed_with_its_checksum(tmp_path):
    """zarr skips chunks equal to the fill value by default; then a missing chunk could not be
    told from a deleted one. The store writes them all, and lists every file with its sha256."""
    import json

    s = EpisodeStore.create(tmp_path / "z.zarr", fps=10)
    eps = episodes([3, 4])
    for e in eps:
        e.data["reward"] = np.zeros(len(e), np.float32)
    s.append(iter(eps), src("a"))
    assert (s.path / "data" / "reward" / "0").is_file()
    assert (s.path / "meta" / "episode_start_time_ns" / "0").is_file()  # all zeros too
    listed = json.loads((s.path / ".sefa-checksums.json").read_text())["files"]
    on_disk = {str(p.relative_to(s.path)) for p in s.path.rglob("*") if p.is_file()}
    assert set(listed) == on_disk - {".sefa-checksums.json"}
    for rel, (size, digest) in listed.items():
        data = (s.path / rel).read_bytes()
        assert len(data) == size and hashlib.sha256(data).hexdigest() == digest, rel
    # an append rehashes what it wrote: the list stays exact
    more = episodes([2], seed=3)
    more[0].data["reward"] = np.zeros(2, np.float32)
    s.append(iter(more), src("b"))
    listed = json.loads((s.path / ".sefa-checksums.json").read_text())["files"]
    for rel, (size, digest) in listed.items():
        assert hashlib.sha256((s.path / rel).read_bytes()).hexdigest() == digest, rel


def test_a_missing_chunk_is_never_read_as_zeros(store):
    (store.path / "data" / "action" / "0.0").unlink()
    for mode in ("r", "a"):
        with pytest.raises(SefaInputError, match=r"data/action: chunk 0.0 is missing \(zarr would "
                                                 r"read it as zeros\): the store is damaged"):
            EpisodeStore.open(store.path, mode=mode)


def test_a_store_without_checksums_opens_and_gets_them_at_its_next_append(store):
    """Stores written before checksums existed: the episode checks still run."""
    (store.path / ".sefa-checksums.json").unlink()
    s = EpisodeStore.open(store.path)
    assert s.verification["checksums"] is False and s.n_episodes == 3
    s.append(iter(episodes([2], seed=4)), src("z"))
    assert EpisodeStore.open(store.path, verify="full").verification["files_hashed"] > 10


def test_episode_index_and_attributes_are_checked(store):
    import json

    attrs = json.loads((store.path / ".zattrs").read_text())
    attrs["sources"][0]["episodes"] = [0, 7]
    (store.path / ".sefa-checksums.json").unlink()  # so that the attribute check itself speaks
    (store.path / ".zattrs").write_text(json.dumps(attrs))
    with pytest.raises(SefaInputError, match="sources: the sources account for 7 episodes, "
                                             "meta/episode_ends has 3"):
        EpisodeStore.open(store.path)


def test_two_writers_never_interleave(store, tmp_path):
    """An append holds the store's write lock; a second process is refused, not interleaved."""
    from sefa_data.store import journal as store_journal

    code = textwrap.dedent(f"""
        import sys
        from sefa_data.store import journal as store_journal
        from pathlib import Path
        print(store_journal.try_lock(Path({str(store.path)!r})))
    """)
    store_journal.lock(store.path)
    try:
        out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True)
        assert out.stdout.strip() == "False", out.stderr
    finally:
        store_journal.unlock(store.path)
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True)
    assert out.stdout.strip() == "True", out.stderr


def test_zarrs_io_loop_is_stopped_before_zarrs_own_exit_handler(tmp_path):
    """zarr's exit handler closes its IO loop after a 0.2 s join, which on a busy machine
    prints 'Cannot close a running event loop' after a successful command; ours
    (sefa_data/store/zarr_store.py) stops it first. An exit function registered before zarr is
    imported runs after both and sees what they left: nothing."""
    code = textwrap.dedent(f"""
        import atexit
        def last():
            from zarr.core import sync
            print("left:", sync.loop[0], sync.iothread[0])
        atexit.register(last)
        import numpy as np, zarr
        import sefa_data.store.zarr_store
        zarr.open_group({str(tmp_path / 'x.zarr')!r}, mode="w").create_array("a", data=np.arange(3))
        from zarr.core import sync
        assert sync.loop[0] is not None and sync.loop[0].is_running()
        sync.loop[0].call_soon_threadsafe(__import__("time").sleep, 0.5)  # zarr's join would time out
    """)
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO,
                       env={**os.environ, "PYTHONPATH": str(REPO)})
    assert r.returncode == 0 and "Traceback" not in r.stderr, r.stderr
    assert "left: None None" in r.stdout
