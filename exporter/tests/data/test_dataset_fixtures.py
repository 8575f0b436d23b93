"""The dataset fixtures shared with the Rust readers (tests/fixtures/datasets/, written by
scripts/make-dataset-fixtures.py): the Python loaders must still give the cameras, near/far and
background recorded in each folder's expected.json, which the Rust readers are tested against
too (capture/tests/readers.rs). A change to a loader that fails here needs the fixtures
regenerated and the Rust reader changed to match."""

from __future__ import annotations

import json
import re
import shutil
import struct

import numpy as np
import pytest

from scnerf_export.data.dataparsers import colmap_binary
from scnerf_export.data.datasets import load_scene
from scnerf_export.evaluate import metrics

from conftest import REPO

FIXTURES = REPO / "tests" / "fixtures" / "datasets"
FOLDERS = sorted(p.parent.name for p in FIXTURES.glob("*/expected.json"))


def test_every_format_has_a_fixture():
    assert FOLDERS == ["blender", "colmap", "dtu", "llff", "nerfstudio"]


def expected_of(folder: str) -> dict:
    return json.loads((FIXTURES / folder / "expected.json").read_text())


@pytest.mark.filterwarnings("ignore:.*(missing|no image).*:UserWarning")
@pytest.mark.parametrize("folder", FOLDERS)
def test_loader_matches_expected(folder):
    assert_loads_as(folder, expected_of(folder))


@pytest.mark.filterwarnings("ignore:.*(missing|no image).*:UserWarning")
def test_the_binary_colmap_model_gives_the_text_models_cameras():
    assert not list((FIXTURES / "colmap_binary").rglob("*.txt")), "the binary fixture must hold no text model"
    assert_loads_as("colmap_binary", expected_of("colmap"))


def assert_loads_as(folder: str, expected: dict):
    scene = load_scene(FIXTURES / folder, expected["format"])
    assert scene.near == pytest.approx(expected["near"], rel=1e-12)
    assert scene.far == pytest.approx(expected["far"], rel=1e-12)
    assert list(scene.background) == expected["background"]
    assert list(scene.views) == [v["name"] for v in expected["views"]]
    for want in expected["views"]:
        cam = scene.views[want["name"]].camera
        assert (cam.width, cam.height) == (want["width"], want["height"])
        np.testing.assert_allclose(cam.K, want["K"], rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(cam.w2c, want["w2c"], rtol=1e-12, atol=1e-12)
        assert (FIXTURES / folder / want["image"]).is_file()


def test_metrics_fixture_matches_metrics_py():
    data = json.loads((FIXTURES / "metrics.json").read_text())
    gt = np.array(data["gt"]).reshape(data["shape"])
    pred = np.array(data["pred"]).reshape(data["shape"])
    assert metrics.psnr(pred, gt) == pytest.approx(data["psnr"], rel=1e-12)
    assert metrics.ssim(pred, gt) == pytest.approx(data["ssim"], rel=1e-12)


def test_a_truncated_binary_colmap_model_is_refused_naming_the_file(tmp_path):
    capture = tmp_path / "capture"
    shutil.copytree(FIXTURES / "colmap_binary", capture)
    images = capture / "sparse" / "0" / "images.bin"
    whole = images.read_bytes()
    images.write_bytes(whole[:-5])
    with pytest.raises(ValueError, match="images.bin: truncated binary model"):
        load_scene(capture, "colmap")
    images.write_bytes(struct.pack("<Q", 10**12) + whole[8:])
    with pytest.raises(ValueError, match=r"images.bin: truncated binary model \(record count 1000000000000"):
        load_scene(capture, "colmap")


def test_the_binary_model_ids_are_the_rust_readers():
    """Both readers index COLMAP's model table by the binary model id."""
    rust = (REPO / "capture" / "src" / "readers" / "colmap" / "lens.rs").read_text()
    table = re.search(r"const MODELS: \[\(&str, usize\); \d+\] = \[(.*?)\];", rust, re.S)
    assert table, "MODELS is not in capture/src/readers/colmap/lens.rs"
    rows = re.findall(r'\("([A-Z_]+)", (\d+)\)', table.group(1))
    assert tuple((model, int(n)) for model, n in rows) == colmap_binary.MODELS
