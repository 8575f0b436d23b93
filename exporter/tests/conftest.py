import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


def shared_dir() -> Path:
    return Path(os.environ.get("SCNERF_SHARED", REPO.parent / "shared"))


@pytest.fixture(scope="session")
def public_checkpoint() -> Path:
    path = shared_dir() / "weights" / "mvsnerf-v0.tar"
    if not path.is_file():
        pytest.skip(f"public MVSNeRF checkpoint not found at {path} (../shared is absent on this machine)")
    return path


@pytest.fixture(scope="session")
def parity_fixtures() -> Path:
    return REPO / "tests" / "fixtures" / "parity"
