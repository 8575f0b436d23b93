"""The rules the Python side shares with the Rust capture crate, against tests/fixtures/rules/
(written by scripts/make-rule-fixtures.py; capture/tests/rules.rs holds the Rust side to the same
files): which files are images and which image set a capture is read from (image_files.json:
the parsers' ``is_image`` and LLFF's listing and ``images_N``; the Python client asks the server,
POST /v1/captures/plan), the API's pose conventions, look_at and resized cameras (cameras.json),
source ranking (source_ranking.json). The depth range's fixture is test_depth_range.py's. A rule
changed on one side alone fails that side's tests."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from scnerf_export.cameras import Camera, canonical_w2c, look_at, rank_sources
from scnerf_export.data.dataparsers.llff import LlffParser
from scnerf_export.data.scene import is_image, list_images
from scnerf_export.train.refine_capture import MAX_SOURCE_PIXELS, CaptureError, image_sets, pick_image_set

from conftest import REPO

RULES = REPO / "tests" / "fixtures" / "rules"
IMAGE_FILES = json.loads((RULES / "image_files.json").read_text())
CAMERAS = json.loads((RULES / "cameras.json").read_text())
RANKING = json.loads((RULES / "source_ranking.json").read_text())


def build(root: Path, files: dict) -> None:
    """PNG bytes of each size (whatever the extension: readers go by the bytes), a byte for the rest."""
    for rel, size in files.items():
        path = root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        if size is None:
            path.write_bytes(b"x")
        else:
            Image.new("RGB", tuple(size)).save(path, format="PNG")


def test_which_files_are_images(tmp_path):
    names = IMAGE_FILES["names"]
    build(tmp_path, {n["name"]: None for n in names})
    for n in names:
        assert is_image(Path(n["name"])) == n["image_extension"], n
    assert [p.name for p in list_images(tmp_path)] == sorted(n["name"] for n in names if n["image"])


@pytest.mark.parametrize("case", IMAGE_FILES["captures"], ids=lambda c: c["name"])
def test_image_lists_and_the_downscaled_set_llff_reads(tmp_path, case):
    build(tmp_path, case["files"])
    for folder, images in case["images"].items():
        assert [p.name for p in list_images(tmp_path / folder)] == images, folder
    poses = len(case["images"].get("images", []))
    for want in case["picks"]:
        downscale = want.get("downscale")
        if downscale and downscale > 1 and poses:
            # The exporter's LLFF parser reads images_N for scale 1/N when it holds every image.
            files = LlffParser._downscaled_set(tmp_path, 1 / downscale, poses)
            assert (files[0].parent.name if files else None) == want.get("set"), want


@pytest.mark.parametrize("case", IMAGE_FILES["captures"], ids=lambda c: c["name"])
def test_the_image_set_refine_reads(tmp_path, case):
    build(tmp_path, case["files"])
    sets = image_sets(tmp_path, "llff")
    for want in case["picks"]:
        if want.get("error"):
            with pytest.raises(CaptureError):
                pick_image_set(sets, want["downscale"], MAX_SOURCE_PIXELS)
            continue
        chosen = pick_image_set(sets, want.get("downscale"), want.get("fit", MAX_SOURCE_PIXELS))
        name = None if chosen is None else "images" if chosen.factor == 1 else f"images_{chosen.factor}"
        assert name == want["set"], want


@pytest.mark.parametrize("case", CAMERAS["poses"], ids=lambda c: f"{c['kind']}-{c['axes']}")
def test_every_pose_convention_gives_the_canonical_pose(case):
    w2c = canonical_w2c(case["matrix"], case["kind"], case["axes"])
    np.testing.assert_allclose(w2c, case["w2c"], rtol=0, atol=1e-12)
    camera = Camera.from_pose(np.eye(3), case["matrix"], 8, 6, case["kind"], case["axes"])
    np.testing.assert_allclose(camera.w2c, case["w2c"], rtol=0, atol=1e-12)


def test_look_at_is_the_fixtures():
    for case in CAMERAS["look_at"]:
        np.testing.assert_allclose(look_at(case["eye"], case["target"], case["up"]), case["w2c"], rtol=0, atol=1e-12)


def test_resized_cameras_are_the_fixtures():
    for case in CAMERAS["resized"]:
        c, r = case["camera"], case["resized"]
        K = np.array([[c["fx"], 0, c["cx"]], [0, c["fy"], c["cy"]], [0, 0, 1]], dtype=np.float64)
        got = Camera(K, np.eye(4), c["width"], c["height"]).resized(r["width"], r["height"])
        assert (got.width, got.height) == (r["width"], r["height"])
        np.testing.assert_allclose(
            [got.K[0, 0], got.K[1, 1], got.K[0, 2], got.K[1, 2]], [r["fx"], r["fy"], r["cx"], r["cy"]], atol=1e-9
        )


@pytest.mark.parametrize("case", RANKING["cases"], ids=lambda c: c["name"])
def test_source_ranking_is_the_fixtures(case):
    def camera(w2c):
        return Camera(np.eye(3), np.array(w2c), 8, 6)

    ranked = rank_sources(camera(case["target"]), [camera(m) for m in case["candidates"]])
    assert ranked == case["ranked"]
