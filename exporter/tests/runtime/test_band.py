"""The band's colours from the sources (runtime/band.py), and its fixture for the server's twin
(the same cases as server/src/pipeline/band.rs's tests)."""

import json

import numpy as np

from scnerf_export.export.fixtures import write_band_case
from scnerf_export.runtime.band import Sources, fill_from_sources

from conftest import REPO

# Two sources at the origin looking down +z (f = 1, centre (1.5, 1)), 4x3 and 2x3 (padded to 4):
# source 0 a red ramp along x (x / 4) over green 0.9, source 1 grey 0.5. Pixel 0 at image x = 1 (seen
# by both: red 0.375, green 0.7), pixel 1 at x = 1.75 (source 0 alone: red 0.4375, green 0.9), both
# at depth 2 and opacity 0.5.
EVERY = 0.5 * np.array([0.375, 0.7, 0.7])
SEEN_BY_ONE = 0.5 * np.array([0.4375, 0.9, 0.9])
RAYS = (-0.5, 0.25)


def ramp_sources(padding: float = 0.0) -> Sources:
    images = np.zeros((2, 3, 3, 4), np.float32)
    images[0, 0] = np.arange(4) / 4
    images[0, 1:] = 0.9
    images[1, :, :, :2] = 0.5
    images[1, :, :, 2:] = padding
    intrinsics = np.tile(np.array([[1.0, 0.0, 1.5], [0.0, 1.0, 1.0], [0.0, 0.0, 1.0]], np.float32), (2, 1, 1))
    return Sources(images, [(4, 3), (2, 3)], intrinsics, np.tile(np.eye(4, dtype=np.float32), (2, 1, 1)))


def fill(sources: Sources, network, rays=RAYS, depth=(2.0, 2.0), rule="when_dark"):
    n = len(rays)
    return fill_from_sources(
        np.array(network, np.float32),
        np.array(depth, np.float32),
        np.full(n, 0.5, np.float32),
        np.zeros((n, 3), np.float32),
        np.array([[x, 0.0, 1.0] for x in rays], np.float32),
        sources,
        rule,
    )


def test_a_dark_band_takes_the_colour_of_the_sources_that_see_it_times_opacity():
    rgb, recoloured = fill(ramp_sources(), [EVERY, 0.5 * SEEN_BY_ONE])
    assert recoloured.tolist() == [False, True]
    np.testing.assert_allclose(rgb, [EVERY, SEEN_BY_ONE], atol=1e-6)


def test_a_band_within_the_ratio_of_the_rest_keeps_the_networks_colour_unless_the_bundle_always_fills():
    network = np.array([EVERY, 0.95 * SEEN_BY_ONE], np.float32)
    rgb, recoloured = fill(ramp_sources(), network)
    assert not recoloured.any()
    np.testing.assert_array_equal(rgb, network)
    rgb, recoloured = fill(ramp_sources(), network, rule="always")
    assert recoloured.tolist() == [False, True]
    np.testing.assert_allclose(rgb, [EVERY, SEEN_BY_ONE], atol=1e-6)


def test_without_pixels_every_source_sees_nothing_is_recoloured():
    network = np.array([[0.0] * 3, 0.5 * SEEN_BY_ONE], np.float32)  # pixel 0 behind both cameras
    rgb, recoloured = fill(ramp_sources(), network, depth=(-1.0, 2.0))
    assert not recoloured.any()
    np.testing.assert_array_equal(rgb, network)


def test_a_pixel_no_source_sees_takes_the_nearest_pixels_of_the_sources_in_a_dark_band():
    # Pixel 2 at image x = 3.5: outside both images, in front of both. Their nearest pixels: source
    # 0's last column (red 0.75, green 0.9), source 1's (grey 0.5).
    network = [EVERY, 0.5 * SEEN_BY_ONE, [0.0] * 3]
    rgb, recoloured = fill(ramp_sources(), network, rays=(*RAYS, 2.0), depth=(2.0, 2.0, 2.0))
    assert recoloured.tolist() == [False, True, True]
    np.testing.assert_allclose(rgb, [EVERY, SEEN_BY_ONE, 0.5 * np.array([0.625, 0.7, 0.7])], atol=1e-6)


def test_padding_beyond_a_sources_size_is_outside_it():
    # x = 2 lies in source 1's padding (bright 1.0): source 0 alone sees it.
    rgb, recoloured = fill(ramp_sources(padding=1.0), [EVERY, [0.0] * 3], rays=(-0.5, 0.5))
    assert recoloured.tolist() == [False, True]
    np.testing.assert_allclose(rgb, [EVERY, 0.5 * np.array([0.5, 0.9, 0.9])], atol=1e-6)


def test_the_committed_band_fixture_is_what_the_band_computes_today(tmp_path):
    committed = json.loads((REPO / "tests" / "fixtures" / "parity" / "band.json").read_text())
    write_band_case(tmp_path, committed["seed"])
    fresh = json.loads((tmp_path / "band.json").read_text())
    assert fresh["band_pixels"] == committed["band_pixels"] > 0
    np.testing.assert_allclose(fresh["expected_rgb"], committed["expected_rgb"], atol=1e-7)
    np.testing.assert_array_equal(fresh["raw"]["rgb"], committed["raw"]["rgb"])
