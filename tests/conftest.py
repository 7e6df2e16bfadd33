from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The real recordings in ../shared/data; tests that need them skip when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real recordings not found at {SHARED_DATA} (a user's clone has no ../shared)")
    return SHARED_DATA


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
