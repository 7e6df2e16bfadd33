"""Does Diffusion Policy's own ReplayBuffer load a sefa store? Run with a Python that has
Diffusion Policy's zarr 2 (zarr 2.18, numcodecs < 0.16), not sefa's venv:

    python -m venv /tmp/dp && /tmp/dp/bin/pip install "zarr==2.18.3" "numcodecs<0.16" numpy
    /tmp/dp/bin/python scripts/dp_replay_check.py DP_CHECKOUT STORE [COMMIT ...]

DP_CHECKOUT is a git clone of real-stanford/diffusion_policy; each COMMIT's
diffusion_policy/common/replay_buffer.py (default: 27395b7 of 2023 and 5ba07ac of 2024) is
loaded as it is and runs `copy_from_path` (numpy backend and zarr MemoryStore backend) and
`create_from_path`. Exit 1 when any of them fails or disagrees with the store's arrays.
"""
import importlib.util
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import zarr


def load_replay_buffer(repo: str, commit: str):
    source = subprocess.run(["git", "-C", repo, "show",
                             f"{commit}:diffusion_policy/common/replay_buffer.py"],
                            check=True, capture_output=True, text=True).stdout
    path = Path(tempfile.mkdtemp()) / f"replay_buffer_{commit}.py"
    path.write_text(source)
    spec = importlib.util.spec_from_file_location(path.stem, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.ReplayBuffer


def check(rb, store: str, ends: np.ndarray, data: dict) -> str:
    assert np.array_equal(rb.episode_ends[:], ends), "episode_ends differ"
    for key, values in data.items():
        assert np.array_equal(rb[key][:], values), f"data/{key} differs"
    return f"{rb.n_episodes} episodes, {rb.n_steps} steps, keys {sorted(rb.keys())}"


def main(repo: str, store: str, *commits: str) -> int:
    root = zarr.open(store, "r")
    ends = root["meta/episode_ends"][:]
    data = {k: root["data"][k][:] for k in root["data"].array_keys()}
    masks = {k: int(root["mask"][k][:].sum()) for k in root["mask"].array_keys()} \
        if "mask" in root else {}
    print(f"{store}: zarr {zarr.__version__}, masks kept: {masks}")
    failed = 0
    for commit in commits or ("27395b7", "5ba07ac"):
        ReplayBuffer = load_replay_buffer(repo, commit)
        loaders = {"copy_from_path (numpy)": lambda: ReplayBuffer.copy_from_path(store),
                   "copy_from_path (MemoryStore)": lambda: ReplayBuffer.copy_from_path(
                       store, store=zarr.MemoryStore()),
                   "create_from_path": lambda: ReplayBuffer.create_from_path(store, mode="r")}
        for name, load in loaders.items():
            try:
                line = check(load(), store, ends, data)
                print(f"DP {commit} {name}: OK: {line}")
            except Exception as e:
                failed += 1
                print(f"DP {commit} {name}: FAILED: {e!r}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:]))
