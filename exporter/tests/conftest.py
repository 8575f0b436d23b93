import os
from pathlib import Path

import pytest

from scnerf_export.config import small_config
from scnerf_export.export.bundle import export_bundle
from scnerf_export.rigs import random_model

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


@pytest.fixture(scope="session")
def small_bundle(tmp_path_factory):
    """``small_bundle(variant)``: the small random model of the parity fixtures' seed
    (``random_model(small_config(variant), seed=7)``), its bundle exported once for the whole run,
    and the manifest. Exporting takes most of a test's time: tests that read an export share this
    one and write nothing into its folder."""
    exported = {}

    def get(variant: str = "scnerf"):
        if variant not in exported:
            model = random_model(small_config(variant), seed=7)
            out = tmp_path_factory.mktemp(f"small-{variant}")
            exported[variant] = (model, out, export_bundle(model, out, {"source_checkpoint": None}))
        return exported[variant]

    return get
