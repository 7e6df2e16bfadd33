"""The affine normalizer: DP's limits and gaussian modes, constant dimensions, torch, files."""

import hashlib
import json

import numpy as np
import pytest
import torch

from sefa_data.episode import Episode
from sefa_data.errors import SefaInputError
from sefa_data.normalizer import CONFIG_FILE, STATE_FILE, Normalizer
from sefa_data.store.zarr_store import EpisodeStore, split_masks

# Params are float32, so x * scale + offset is exact only to float32 rounding.
F32 = 2e-6


@pytest.fixture
def data():
    rng = np.random.default_rng(0)
    action = rng.uniform([12, 25], [511, 511], size=(500, 2)).astype(np.float32)
    keypoint = rng.normal(300, [[5, 50]] * 9, size=(500, 9, 2)).astype(np.float32)
    state = np.concatenate([rng.normal(0, 3, (500, 2)), np.full((500, 1), 7.5)], axis=1)
    state = state.astype(np.float32)  # the last dimension is constant
    return {"action": action, "keypoint": keypoint, "state": state}


def test_limits_maps_min_and_max_to_minus_one_and_one(data):
    n = Normalizer.fit(data, {"action": "limits", "keypoint": "limits"})
    for key in ("action", "keypoint"):
        y = n.normalize(key, data[key])
        assert y.dtype == np.float32
        np.testing.assert_allclose(y.min(0), -1.0, atol=F32)  # per element of the frame shape
        np.testing.assert_allclose(y.max(0), 1.0, atol=F32)
        lo = data[key].argmin(0)
        assert abs(n.normalize(key, data[key][lo.flat[0]])[(0,) * (y.ndim - 1)] + 1) <= F32


def test_round_trip(data):
    n = Normalizer.fit(data, {"action": "limits", "keypoint": "gaussian", "state": "limits"})
    for key, x in data.items():
        np.testing.assert_allclose(n.unnormalize(key, n.normalize(key, x)), x, rtol=1e-5, atol=1e-4)


def test_constant_dims_map_to_zero_and_stay_finite(data):
    for mode in ("limits", "gaussian"):
        n = Normalizer.fit(data, {"state": mode})
        y = n.normalize("state", data["state"])
        assert np.isfinite(y).all()
        np.testing.assert_array_equal(y[:, 2], 0.0)
        assert n.params["state"].scale[2] == 1.0
        np.testing.assert_allclose(n.unnormalize("state", y)[:, 2], 7.5)
    tiny = {"x": np.array([[1.0], [1.0 + 5e-5]])}  # range below range_eps: still constant
    assert Normalizer.fit(tiny, {"x": "limits"}).params["x"].scale[0] == 1.0


def test_gaussian(data):
    n = Normalizer.fit(data, {"keypoint": "gaussian"})
    y = n.normalize("keypoint", data["keypoint"])
    np.testing.assert_allclose(y.mean(0), 0.0, atol=1e-4)
    np.testing.assert_allclose(y.std(0), 1.0, atol=1e-4)


def test_torch_and_numpy_agree_over_leading_dims(data):
    n = Normalizer.fit(data, {"action": "limits", "keypoint": "gaussian"})
    x = data["keypoint"][:64].reshape(8, 8, 9, 2)  # (B, T, 9, 2)
    want = n.normalize("keypoint", x)
    got = n.normalize("keypoint", torch.from_numpy(x))
    assert isinstance(got, torch.Tensor) and got.dtype == torch.float32
    np.testing.assert_allclose(got.numpy(), want, rtol=1e-6, atol=1e-6)
    back = n.unnormalize("keypoint", got.double())
    assert back.dtype == torch.float64
    np.testing.assert_allclose(back.numpy(), x, rtol=1e-5, atol=1e-3)
    ints = np.array([[100, 200]], dtype=np.int64)
    np.testing.assert_allclose(n.normalize("action", torch.from_numpy(ints)).numpy(),
                               n.normalize("action", ints), rtol=1e-6)
    with pytest.raises(SefaInputError, match="frame shape"):
        n.normalize("keypoint", x.reshape(8, 8, 18))
    with pytest.raises(SefaInputError, match="no such key"):
        n.normalize("nope", x)


def test_unknown_mode_is_an_error(data):
    with pytest.raises(SefaInputError, match="unknown normalizer mode"):
        Normalizer.fit(data, {"action": "minmax"})


def test_save_load_round_trip(tmp_path, data):
    n = Normalizer.fit(data, {"action": "limits", "keypoint": "gaussian", "state": "limits"})
    assert set(n.state_dict()) == {f"{k}.{p}" for k in data for p in ("scale", "offset")}
    n.save(tmp_path)
    config = json.loads((tmp_path / CONFIG_FILE).read_text())
    assert config["keys"]["keypoint"] == {"mode": "gaussian", "shape": [9, 2]}
    m = Normalizer.load(tmp_path)
    for key, x in data.items():
        assert m.params[key].mode == n.params[key].mode
        np.testing.assert_array_equal(m.normalize(key, x), n.normalize(key, x))


def test_missing_corrupt_or_mismatched_files_name_the_file(tmp_path, data):
    n = Normalizer.fit(data, {"action": "limits"})
    with pytest.raises(SefaInputError, match=STATE_FILE.replace(".", r"\.") + ".*no such file"):
        Normalizer.load(tmp_path)
    n.save(tmp_path)
    state, config = tmp_path / STATE_FILE, tmp_path / CONFIG_FILE
    good_state, good_config = state.read_bytes(), config.read_text()

    state.write_bytes(b"\x00garbage")
    with pytest.raises(SefaInputError, match=r"normalizer\.safetensors.*not a readable"):
        Normalizer.load(tmp_path)
    state.write_bytes(good_state)

    config.write_text("{not json")
    with pytest.raises(SefaInputError, match=r"normalizer\.json.*not valid JSON"):
        Normalizer.load(tmp_path)

    def with_config(change):
        bad = json.loads(good_config)
        change(bad)
        config.write_text(json.dumps(bad))

    with_config(lambda c: c["keys"]["action"].update(shape=[3]))
    with pytest.raises(SefaInputError, match=r"normalizer\.safetensors: action: .*json says"):
        Normalizer.load(tmp_path)
    with_config(lambda c: c["keys"].update(state={"mode": "limits", "shape": [3]}))
    with pytest.raises(SefaInputError, match=r"safetensors: the arrays do not match"):
        Normalizer.load(tmp_path)
    for change in (lambda c: c.update(sefa_normalizer=99),
                   lambda c: c["keys"]["action"].update(mode="minmax")):
        with_config(change)
        with pytest.raises(SefaInputError, match=r"normalizer\.json: not a sefa normalizer"):
            Normalizer.load(tmp_path)
    config.write_text("[1, 2]")
    with pytest.raises(SefaInputError, match=r"normalizer\.json: not a sefa normalizer"):
        Normalizer.load(tmp_path)


def test_the_policys_normalizer_ignores_valid_episodes(tmp_path):
    # the fit a training run makes (PolicyData.fit_normalizer: training split only)
    from sefa_model.config import load_train_config
    from sefa_model.policy.model import resolve_shapes
    from sefa_model.data.windows import PolicyData

    rng = np.random.default_rng(0)
    eps = [Episode({"action": rng.uniform(-1, 1, (10, 2)).astype(np.float32),
                    "cam": np.zeros((10, 8, 8, 3), np.uint8)}, source="t") for _ in range(10)]
    store = EpisodeStore.create(tmp_path / "s.zarr", fps=10)
    valid = np.flatnonzero(split_masks(10, 0.1, 42)[1])  # the split the store will draw
    for i in valid:
        eps[i].data["action"] *= 100  # extreme values only in the validation episodes
    store.append(iter(eps), {"path": "t", "sha256": hashlib.sha256(b"t").hexdigest(), "size": 1})
    np.testing.assert_array_equal(np.flatnonzero(store.mask("valid")), valid)

    cfg = resolve_shapes(load_train_config(None, ["policy.horizon=4", "policy.n_action_steps=2"]), store)
    n = PolicyData(cfg, store, None).fit_normalizer()
    train = np.concatenate([e.data["action"] for i, e in enumerate(eps) if i not in valid])
    np.testing.assert_allclose(n.normalize("action", train).min(0), -1, atol=F32)
    np.testing.assert_allclose(n.normalize("action", train).max(0), 1, atol=F32)
    assert "cam" not in n  # images are not normalized: the processor scales them to [0, 1]


def test_the_train_configs_range_eps_decides_which_dimensions_are_constant(tmp_path):
    # a Meta-World gripper opening that only jitters (0.997..1.000 in reach's demonstrations):
    # stretched to [-1, 1] by default; shifted, not stretched, with normalizer.range_eps=0.01
    from sefa_data.errors import ConfigError
    from sefa_data.normalizer import DEFAULT_RANGE_EPS
    from sefa_model.config import NormalizerConfig, load_train_config
    from sefa_model.data.windows import PolicyData
    from sefa_model.policy.model import resolve_shapes

    assert NormalizerConfig().range_eps == DEFAULT_RANGE_EPS  # the config's default is the fit's
    rng = np.random.default_rng(0)
    eps = [Episode({"action": rng.uniform(-1, 1, (10, 2)).astype(np.float32),
                    "state": np.stack([rng.uniform(0.997, 1.0, 10), rng.uniform(0, 1, 10)],
                                      axis=1).astype(np.float32)}, source="t") for _ in range(10)]
    store = EpisodeStore.create(tmp_path / "s.zarr", fps=10)
    store.append(iter(eps), {"path": "t", "sha256": hashlib.sha256(b"t").hexdigest(), "size": 1})
    base = ["policy.horizon=4", "policy.n_action_steps=2", "shape_meta.obs_keys=[state]"]
    train = np.concatenate([e.data["state"] for i, e in enumerate(eps)
                            if store.mask("train")[i]])
    for overrides, jitter_scale in (([], 2 / np.ptp(train[:, 0])),
                                    (["normalizer.range_eps=0.01"], 1.0)):
        cfg = resolve_shapes(load_train_config(None, base + overrides), store)
        n = PolicyData(cfg, store, None).fit_normalizer()
        scale = n.params["state"].scale
        np.testing.assert_allclose(scale, [jitter_scale, 2 / np.ptp(train[:, 1])], rtol=1e-5)
    with pytest.raises(ConfigError, match="range_eps"):
        load_train_config(None, base + ["normalizer.range_eps=0"])
    # a stage's cache key holds the threshold only when it is not the default, so a workspace
    # trained before the key existed is not made again
    from sefa_model.config import cache_key_dict

    assert cache_key_dict(load_train_config(None, base))["normalizer"] == {
        "action": "limits", "obs": "limits"}
    assert cache_key_dict(load_train_config(None, base + ["normalizer.range_eps=0.01"]))[
        "normalizer"]["range_eps"] == 0.01
