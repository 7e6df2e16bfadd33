"""Importing Diffusion Policy ReplayBuffer stores: the real Push-T store, a zipped copy of part of
it, and small stores written here with zarr for the error cases."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
import zarr
import zarr.storage

from sefa_data.readers import dp_zarr
from sefa_data.episode import Episode
from sefa_data.errors import SefaInputError
from sefa_data.readers.dp_zarr import read_dp_zarr

PUSHT = "pusht_cchi_v7_replay.zarr"
IMAGE_KEY = "observation.images.top"
LOW_DIM = ["action", "keypoint", "n_contacts", "state"]


@dataclass
class PushT:
    """One pass of read_dp_zarr over the whole store (the images are read once per module)."""

    path: Path
    meta: dict
    labels: list[str] = field(default_factory=list)
    lengths: list[int] = field(default_factory=list)
    low_dim: dict[str, list[np.ndarray]] = field(default_factory=dict)
    full: dict[int, Episode] = field(default_factory=dict)  # the spot-checked episodes


def _spot_checked(ends: np.ndarray, block_rows: int) -> set[int]:
    """The first three and the last episode, and two that straddle a block boundary."""
    starts = np.concatenate([[0], ends[:-1]])
    straddling = np.flatnonzero(starts // block_rows != (ends - 1) // block_rows)
    return {0, 1, 2, len(ends) - 1, *straddling[:2].tolist()}


@pytest.fixture(scope="module")
def pusht(shared_data: Path) -> PushT:
    path = shared_data / PUSHT
    root = zarr.open_group(path, mode="r")
    keep = _spot_checked(root["meta/episode_ends"][:], dp_zarr._block_rows(root["data/img"]))
    rec = read_dp_zarr(path, renames={"img": IMAGE_KEY})
    out = PushT(path=path, meta=rec.meta, low_dim={k: [] for k in LOW_DIM})
    for i, ep in enumerate(rec.episodes):
        assert {len(v) for v in ep.data.values()} == {len(ep)}
        assert set(ep.data) == {IMAGE_KEY, *LOW_DIM}
        out.labels.append(ep.label)
        out.lengths.append(len(ep))
        for key in LOW_DIM:
            out.low_dim[key].append(ep.data[key])
        if i in keep:
            out.full[i] = ep
    return out


def test_pusht_episodes(pusht: PushT) -> None:
    ends = zarr.open_group(pusht.path, mode="r")["meta/episode_ends"][:]
    assert len(pusht.lengths) == 206
    assert pusht.lengths == np.diff(ends, prepend=0).tolist()
    assert pusht.labels[:2] == ["episode_0", "episode_1"]


def test_pusht_low_dim_equals_plain_read(pusht: PushT) -> None:
    root = zarr.open_group(pusht.path, mode="r")
    for key in LOW_DIM:
        joined = np.concatenate(pusht.low_dim[key])
        assert joined.dtype == root[f"data/{key}"].dtype
        np.testing.assert_array_equal(joined, root[f"data/{key}"][:])


def test_pusht_spot_checked_episodes_equal_plain_read(pusht: PushT) -> None:
    root = zarr.open_group(pusht.path, mode="r")
    ends = root["meta/episode_ends"][:]
    assert len(pusht.full) >= 5
    for i, ep in pusht.full.items():
        start, end = (ends[i - 1] if i else 0), ends[i]
        image = ep.data[IMAGE_KEY]
        assert image.dtype == np.uint8 and image.shape == (end - start, 96, 96, 3)
        source = root["data/img"][start:end]  # float32 0..255
        assert source.dtype == np.float32
        np.testing.assert_array_equal(image, source)
        for key in LOW_DIM:
            np.testing.assert_array_equal(ep.data[key], root[f"data/{key}"][start:end])


def test_pusht_meta(pusht: PushT) -> None:
    meta = pusht.meta
    assert meta["layout"] == "diffusion_policy_replay_buffer"
    assert meta["zarr_format"] == 2 and meta["store"] == "directory"
    assert meta["n_episodes"] == 206 and meta["steps"] == 25650
    assert "fps" not in meta  # a Diffusion Policy store does not record it
    img = meta["keys"]["img"]
    assert img["key"] == IMAGE_KEY
    assert (img["dtype"], img["dtype_out"]) == ("float32", "uint8")
    assert img["chunks"] == [161, 96, 96, 3] and img["shape"] == [25650, 96, 96, 3]
    assert meta["keys"]["state"]["dtype_out"] == "float32"
    assert meta["keys"]["action"]["compressors"][0]["cname"] == "zstd"


def test_pusht_zip_subset_imports_identically(pusht: PushT, tmp_path: Path) -> None:
    # A .zarr.zip written here with zarr's own ZipStore from the first three Push-T episodes
    # (a zip of the whole store would take long to write); source chunking and dtypes kept.
    source = zarr.open_group(pusht.path, mode="r")
    ends = source["meta/episode_ends"][:3]
    path = tmp_path / "pusht_part.zarr.zip"
    store = zarr.storage.ZipStore(path, mode="w")
    root = zarr.open_group(store, mode="w", zarr_format=2)
    for key in ["img", *LOW_DIM]:
        arr = source[f"data/{key}"]
        root.create_array(f"data/{key}", data=arr[: ends[-1]], chunks=arr.chunks)
    root.create_array("meta/episode_ends", data=ends)
    store.close()

    rec = read_dp_zarr(path, renames={"img": IMAGE_KEY})
    episodes = list(rec.episodes)
    assert rec.meta["store"] == "zip" and len(episodes) == 3
    for i, ep in enumerate(episodes):
        expected = pusht.full[i]
        assert ep.data.keys() == expected.data.keys()
        for key, values in ep.data.items():
            assert values.dtype == expected.data[key].dtype
            np.testing.assert_array_equal(values, expected.data[key])


def test_keys_picks_arrays(shared_data: Path) -> None:
    rec = read_dp_zarr(shared_data / PUSHT, keys=["state", "action"], renames={"state": "s"})
    ep = next(rec.episodes)
    assert set(ep.data) == {"action", "s"}
    assert rec.meta["keys"]["img"]["key"] is None  # present in the store, not read


def test_stopping_early_releases_the_store(shared_data: Path) -> None:
    episodes = read_dp_zarr(shared_data / PUSHT).episodes
    assert len(next(episodes)) == 161
    episodes.close()  # must return: the read-ahead threads are stopped, the store closed


# ----------------------------------------------------------------------------- small stores

def _write_store(path: Path, data: dict[str, np.ndarray], ends: np.ndarray,
                 chunk_rows: int = 4) -> Path:
    """A small ReplayBuffer store, written here with zarr (format 2, as Diffusion Policy does)."""
    store = (zarr.storage.ZipStore(path, mode="w") if path.suffix == ".zip"
             else zarr.storage.LocalStore(path))
    root = zarr.open_group(store, mode="w", zarr_format=2)
    for key, values in data.items():
        chunks = (chunk_rows, *values.shape[1:]) if values.ndim else ()
        root.create_array(f"data/{key}", data=values, chunks=chunks)
    root.create_array("meta/episode_ends", data=np.asarray(ends))
    store.close()
    return path


def _small(n: int = 30) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(1)
    return {"action": rng.normal(size=(n, 2)).astype(np.float32),
            "img": rng.integers(0, 256, (n, 16, 16, 3)).astype(np.float32),
            "cam": rng.integers(0, 256, (n, 20, 24, 1), dtype=np.uint8),
            "tiny": rng.integers(0, 256, (n, 8, 8, 3)).astype(np.float32)}  # too small: no image


def test_episodes_across_many_blocks(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    data, ends = _small(), np.array([3, 4, 11, 12, 25, 30])
    path = _write_store(tmp_path / "s.zarr", data, ends, chunk_rows=4)
    monkeypatch.setattr(dp_zarr, "_BLOCK_BYTES", 1)  # one 4-row chunk per block
    episodes = list(read_dp_zarr(path).episodes)
    assert [len(e) for e in episodes] == [3, 1, 7, 1, 13, 5]
    starts = np.concatenate([[0], ends[:-1]])
    for ep, start, end in zip(episodes, starts, ends):
        for key, values in data.items():
            np.testing.assert_array_equal(ep.data[key], values[start:end])
    dtypes = {k: str(v.dtype) for k, v in episodes[0].data.items()}
    assert dtypes == {"action": "float32", "img": "uint8", "cam": "uint8", "tiny": "float32"}


def _error(path: Path, **kwargs) -> SefaInputError:
    with pytest.raises(SefaInputError) as info:
        list(read_dp_zarr(path, **kwargs).episodes)
    assert "\n" not in str(info.value)
    return info.value


def test_missing_path(tmp_path: Path) -> None:
    assert _error(tmp_path / "nope.zarr").what == "file not found"


def test_not_a_store(tmp_path: Path) -> None:
    (tmp_path / "empty.zarr").mkdir()
    assert "not a Zarr store" in _error(tmp_path / "empty.zarr").what
    (tmp_path / "text.zarr.zip").write_text("hello")
    assert "not a Zarr store" in _error(tmp_path / "text.zarr.zip").what


def test_missing_episode_ends(tmp_path: Path) -> None:
    store = zarr.storage.LocalStore(tmp_path / "x.zarr")
    root = zarr.open_group(store, mode="w", zarr_format=2)
    root.create_array("data/action", data=np.zeros((3, 2)))
    assert _error(tmp_path / "x.zarr").key == "meta"


def test_episode_ends_must_be_integers(tmp_path: Path) -> None:
    path = _write_store(tmp_path / "f.zarr", _small(10), np.array([4.0, 10.0]))
    err = _error(path)
    assert err.key == "meta/episode_ends" and "integer" in err.what


def test_episode_ends_must_increase(tmp_path: Path) -> None:
    path = _write_store(tmp_path / "i.zarr", _small(10), np.array([4, 4, 10]))
    err = _error(path)
    assert (err.what, err.where) == ("not strictly increasing (4 then 4)", "index 1")


def test_episode_ends_must_cover_every_array(tmp_path: Path) -> None:
    data = _small(10)
    data["state"] = np.zeros((9, 3), np.float32)
    err = _error(_write_store(tmp_path / "c.zarr", data, np.array([4, 10])))
    assert err.key == "data/state" and "has 9 steps" in err.what


def test_unknown_rename_source(tmp_path: Path) -> None:
    path = _write_store(tmp_path / "r.zarr", _small(10), np.array([10]))
    err = _error(path, renames={"image": "observation.images.top"})
    assert err.what == "no array 'image' under data/; it has: action, cam, img, tiny"
    assert "no array 'pos'" in _error(path, keys=["pos"]).what
    assert "both be named 'action'" in _error(path, renames={"img": "action"}).what


@pytest.mark.parametrize("bad", [3.5, 256.0, -1.0, np.nan])
def test_float_image_must_be_whole_0_255(tmp_path: Path, bad: float) -> None:
    data = _small(12)
    data["img"][7, 3, 2, 1] = bad
    err = _error(_write_store(tmp_path / "b.zarr", data, np.array([5, 12])))
    assert err.key == "data/img" and err.where == "frame 7"
    assert "not a whole number in 0..255" in err.what


def test_nan_in_low_dim(tmp_path: Path) -> None:
    data = _small(12)
    data["action"][9, 1] = np.inf
    err = _error(_write_store(tmp_path / "n.zarr", data, np.array([5, 12])))
    assert (err.key, err.where) == ("data/action", "step 9")


def test_codec_not_installed(tmp_path: Path) -> None:
    # Diffusion Policy's image stores use imagecodecs' Jpeg2k; name it in a small store's metadata
    path = _write_store(tmp_path / "j.zarr", _small(4), np.array([4]))
    meta_file = path / "data" / "img" / ".zarray"
    meta = json.loads(meta_file.read_text())
    meta["compressor"] = {"id": "imagecodecs_jpeg2k_not_installed", "level": 50}
    meta_file.write_text(json.dumps(meta))
    err = _error(path)
    assert err.key == "data" and "codec not available" in err.what


def test_fps_from_store_attributes(tmp_path: Path) -> None:
    # a store written by sefa records its rate in the root attributes; take it over
    path = _write_store(tmp_path / "f.zarr", _small(4), np.array([4]))
    zarr.open_group(path, mode="r+").attrs["fps"] = 10
    assert read_dp_zarr(path).meta["fps"] == 10.0
