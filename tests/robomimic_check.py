"""robomimic's own loader (SequenceDataset, robomimic 0.3.0) on a `sefa collect` file, with its
default settings: next_obs loaded, the train and valid filter keys, the env metadata. Shared by
the Lift and the Meta-World collectors' tests: both write through sefa_sim.demo_file.write_demos."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest


def assert_robomimic_reads(path: Path, keys: tuple[str, ...]) -> dict:
    """Every sample robomimic hands out equals the file's arrays; returns the env metadata."""
    try:
        import robomimic.utils.obs_utils as ObsUtils
        from robomimic.utils.dataset import SequenceDataset
    except ImportError as e:
        pytest.skip(f"robomimic is not installed ({e}); pip install --no-deps robomimic==0.3.0 "
                    "(scripts/setup.sh does)")
    import h5py

    ObsUtils.initialize_obs_utils_with_obs_specs({"obs": {"low_dim": list(keys), "rgb": []}})
    with h5py.File(path, "r") as f:
        env_meta = json.loads(f["data"].attrs["env_args"])  # what FileUtils reads
        train = sorted(n.decode() for n in f["mask/train"][()])
        valid = sorted(n.decode() for n in f["mask/valid"][()])
        demos = {name: {k: f["data"][name][k][()] for k in ("actions", "rewards", "dones")}
                 | {f"obs/{k}": f["data"][name]["obs"][k][()] for k in keys}
                 | {f"next_obs/{k}": f["data"][name]["next_obs"][k][()] for k in keys}
                 for name in f["data"]}
    assert sorted(train + valid) == sorted(demos) and train and valid and not set(train) & set(valid)
    for split, names in (("train", train), ("valid", valid)):
        # robomimic's defaults: load_next_obs=True, the whole file cached in memory
        ds = SequenceDataset(hdf5_path=str(path), obs_keys=keys,
                             dataset_keys=("actions", "rewards", "dones"), hdf5_cache_mode="all",
                             filter_by_attribute=split)
        assert len(ds) == sum(len(demos[n]["actions"]) for n in names)
        i = 0
        for name in names:
            demo = demos[name]
            for t in range(len(demo["actions"])):
                item = ds[i]
                i += 1
                # robomimic hands actions out as float32, observations as stored
                got = {"actions": item["actions"][0]}
                got |= {f"obs/{k}": item["obs"][k][0] for k in keys}
                got |= {f"next_obs/{k}": item["next_obs"][k][0] for k in keys}
                for k, value in got.items():
                    np.testing.assert_array_equal(value, demo[k][t].astype(value.dtype), k)
            # next_obs is obs one step later
            for k in keys:
                np.testing.assert_array_equal(demo[f"next_obs/{k}"][:-1], demo[f"obs/{k}"][1:])
    return env_meta
