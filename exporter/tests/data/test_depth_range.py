"""The depth range from the poses (data/depth_range.py), the twin of the capture crate's
(capture/src/depth_range.rs): on the rigs of tests/fixtures/rules/depth_range.json (written by
scripts/make-rule-fixtures.py; capture/tests/rules.rs holds the Rust side to the same file) it
gives the fixture's point, spread and range, and on the real scenes whose range is known it
contains that range and is at most twice as wide, as the Rust tests hold theirs."""

from __future__ import annotations

import json

import numpy as np
import pytest

from scnerf_export.cameras import Camera
from scnerf_export.data import depth_range
from scnerf_export.train.refine_capture import MAX_SOURCE_PIXELS, read_capture

from conftest import REPO

RIGS = json.loads((REPO / "tests" / "fixtures" / "rules" / "depth_range.json").read_text())["rigs"]

SHARED = REPO.parent / "shared" / "data"
needs_shared = pytest.mark.skipif(not SHARED.is_dir(), reason="../shared/data is absent: no scene of known depth range")


@needs_shared
@pytest.mark.parametrize(
    "scene, known",
    [("nerf_synthetic_lego", (2.0, 6.0)), ("dtu_scan37", (2.125, 4.525)), ("llff_horns", (11.17, 168.95))],
)
def test_the_poses_give_a_range_that_contains_the_known_one_and_is_at_most_twice_as_wide(scene, known):
    data = read_capture(SHARED / scene, None, None, MAX_SOURCE_PIXELS).scene  # the image set the server picks
    assert data.near == pytest.approx(known[0], abs=0.01) and data.far == pytest.approx(known[1], abs=0.5)
    near, far = depth_range.from_poses([v.camera for v in data.views.values()])
    assert near <= data.near and far >= data.far, (near, far)
    assert (far - near) / (data.far - data.near) <= 2.0, (near, far)


@pytest.mark.parametrize("rig", RIGS, ids=lambda r: r["name"])
def test_the_rigs_give_the_fixtures_point_spread_and_range(rig):
    cameras = [Camera(np.eye(3), np.array(w2c), 8, 6) for w2c in rig["w2c"]]
    meet, want = depth_range.convergence(cameras), rig["convergence"]
    assert (meet is None) == (want is None), meet
    if want is not None:
        np.testing.assert_allclose(meet[0], want["point"], rtol=0, atol=1e-9)
        assert meet[1] == pytest.approx(want["spread"], rel=1e-9)
    got = depth_range.from_poses(cameras)
    assert got == (None if rig["range"] is None else pytest.approx(tuple(rig["range"]), rel=1e-9))
