from __future__ import annotations

import os
from pathlib import Path

import pytest

# Under pytest-xdist (`make test`), the workers share the cores: each gets its share of them as
# torch's threads, rather than N workers each starting one thread per core. Set before anything
# imports torch, and in the environment, so that the commands a test starts as child processes
# compute with the same thread count as the test's own process.
# A test whose result depends on the count sets it itself (tests/golden_run.py: 1 thread).
_WORKERS = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
if _WORKERS > 1 and "OMP_NUM_THREADS" not in os.environ:
    os.environ["OMP_NUM_THREADS"] = str(max(1, (os.cpu_count() or 1) // _WORKERS))

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


def pytest_collection_modifyitems(config, items) -> None:
    """The `slow` and `sim` markers from tests/markers.py's table (it says why a table)."""
    import markers

    stale = markers.apply(items, pytest.mark.slow, pytest.mark.sim)
    if stale:
        raise pytest.UsageError("tests/markers.py names tests that were not collected (renamed or "
                                "removed?): " + ", ".join(sorted(stale)))


@pytest.hookimpl(tryfirst=True, optionalhook=True)
def pytest_xdist_make_scheduler(config, log):
    """`--dist loadfile` (`make test`): the slow files first (tests/markers.py)."""
    if config.getvalue("dist") != "loadfile":
        return None
    from xdist.scheduler import LoadFileScheduling

    import markers

    return markers.slow_files_first(LoadFileScheduling)(config, log)


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The real recordings in ../shared/data; tests that need them skip when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real recordings not found at {SHARED_DATA} (a user's clone has no ../shared)")
    return SHARED_DATA


# A tiny image flow on Push-T's camera and agent position (the image tests' policy): each
# training takes seconds, so only plumbing is scored, never skill.
TINY_IMAGE_TRAIN = [
    "shape_meta.obs.img.type=rgb", "shape_meta.obs.state.dims=[0,2]", "policy.head=mlp",
    "policy.crop_shape=[84,84]", "policy.mlp_hidden_dims=[32,32]", "policy.time_embed_dim=16",
    "policy.image_feature_dim=16", "training.batch_size=8", "training.max_steps=4",
    "training.val_every=4", "training.checkpoint_every=4", "training.val_sample_windows=4",
    "training.val_batches=1", "training.lr=1e-3", "training.lr_warmup_steps=1",
    "flow.solver=euler", "flow.steps=2",
]


def pusht_image_store(shared_data: Path, tmp: Path) -> Path:
    """The first three real Push-T episodes with their camera images (copied with zarr's own
    writer), ingested into a store at tmp/store.zarr: the image tests' small real dataset."""
    import zarr

    from sefa_data.ingest import IngestOptions, ingest

    src = zarr.open_group(str(shared_data / "pusht_cchi_v7_replay.zarr"), mode="r")
    ends = src["meta/episode_ends"][:3]
    small = tmp / "small.zarr"
    root = zarr.open_group(str(small), mode="w", zarr_format=2)
    for key in ("img", "state", "action"):
        root.create_array(f"data/{key}", data=src["data"][key][: ends[-1]])
    root.create_array("meta/episode_ends", data=ends)
    store = tmp / "store.zarr"
    ingest([small], store, IngestOptions(fps=10))
    return store


@pytest.fixture(scope="session")
def deploy_workspace(shared_data, tmp_path_factory) -> Path:
    """Tiny flow and one-step checkpoints on Push-T low-dim, shared by the deployment tests
    (tests/deploy_helpers.py says how they are made)."""
    from deploy_helpers import make_checkpoints

    return make_checkpoints(shared_data, tmp_path_factory.mktemp("deploy"))


@pytest.fixture(scope="session")
def deploy_exports(deploy_workspace):
    """exports(name, fmt): the deployment tests' exports, each made once per session."""
    from deploy_helpers import Exports

    return Exports(deploy_workspace)
