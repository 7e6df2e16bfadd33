"""A config or stage argument built in code is as strict as one read from YAML: an unknown key
is an error, never silently ignored (benchmarks/bench_serve.py once passed `"t": "zero"` to
`train`, a key that no longer existed, and trained its "one-step" policy with uniform t)."""

from __future__ import annotations

from pathlib import Path

import pytest

from sefa_data.config_io import from_dict
from sefa_data.errors import ConfigError
from sefa_model.config import TrainConfig
from sefa_model.data.couplings import PairSource
from sefa_model.train.loop import train


def test_an_unknown_key_in_a_train_config_dict_built_in_code_is_an_error():
    with pytest.raises(ConfigError, match="flow: unknown key .t."):
        from_dict(TrainConfig, {"flow": {"t": "zero"}})


def test_an_unknown_key_in_a_pair_source_dict_is_an_error(tmp_path):
    with pytest.raises(ConfigError, match="'t'"):
        from_dict(PairSource, {"path": tmp_path, "target": "action", "kind": "sefa_one_step",
                               "t": "zero"})
    with pytest.raises(ConfigError, match="target"):
        from_dict(PairSource, {"path": tmp_path, "target": "actions", "kind": "sefa_one_step"})


def test_train_refuses_couplings_given_as_a_loose_dict(tmp_path):
    with pytest.raises(TypeError, match="PairSource"):
        train(TrainConfig(), tmp_path / "run", tmp_path / "store.zarr", init_from=Path("x"),
              couplings={"path": tmp_path, "target": "action", "t": "zero", "kind": "sefa_one_step"})


def test_couplings_made_under_another_normalizer_or_window_spec_are_refused(tmp_path):
    import numpy as np

    from sefa_data.errors import SefaInputError
    from sefa_model.data.couplings import read_couplings, write_couplings

    spec = {"horizon": 16, "n_obs_steps": 2, "n_action_steps": 8, "action_key": "action",
            "obs": {}, "n_train_windows": 4}
    noise = np.zeros((8, 16, 2), np.float32)
    write_couplings(tmp_path / "c.zarr", noise, noise + 1, np.repeat(np.arange(4), 2),
                    {"normalizer_sha256": "a" * 64, "window_spec": spec})
    same = {"normalizer_sha256": "a" * 64, "window_spec": spec}
    assert read_couplings(tmp_path / "c.zarr", expect=same).action.shape == (8, 16, 2)
    with pytest.raises(SefaInputError, match="another normalizer"):
        read_couplings(tmp_path / "c.zarr", expect={**same, "normalizer_sha256": "b" * 64})
    with pytest.raises(SefaInputError, match="horizon differ"):
        read_couplings(tmp_path / "c.zarr", expect={**same, "window_spec": {**spec, "horizon": 8}})
