"""The dataset fixtures shared with the Rust readers (tests/fixtures/datasets/, written by
scripts/make-dataset-fixtures.py): the Python loaders must still give the cameras, near/far and
background recorded in each folder's expected.json, which the Rust readers are tested against
too (capture/tests/readers.rs). A change to a loader that fails here needs the fixtures
regenerated and the Rust reader changed to match."""

from __future__ import annotations

import json

import numpy as np
import pytest

from scnerf_export.data.datasets import load_scene
from scnerf_export.evaluate import metrics

from conftest import REPO

FIXTURES = REPO / "tests" / "fixtures" / "datasets"
FOLDERS = sorted(p.parent.name for p in FIXTURES.glob("*/expected.json"))


def test_every_format_has_a_fixture():
    assert FOLDERS == ["blender", "colmap", "dtu", "llff", "nerfstudio"]


@pytest.mark.filterwarnings("ignore:.*(missing|no image).*:UserWarning")
@pytest.mark.parametrize("folder", FOLDERS)
def test_loader_matches_expected(folder):
    expected = json.loads((FIXTURES / folder / "expected.json").read_text())
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
