"""The depth range from the poses (data/depth_range.py), the twin of the capture crate's
(capture/src/depth_range.rs): on the real scenes whose range is known it contains that range and
is at most twice as wide, as the Rust tests hold theirs; its margins are the Rust ones."""

from __future__ import annotations

import re

import pytest

from scnerf_export.data import depth_range
from scnerf_export.train.refine_capture import MAX_SOURCE_PIXELS, read_capture

from conftest import REPO

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


def test_the_margins_are_the_servers():
    rust = (REPO / "capture" / "src" / "depth_range.rs").read_text()
    for name in ("NEAR_MARGIN", "OBJECT_FAR_MARGIN", "FORWARD_FAR_MARGIN", "OBJECT_SPREAD"):
        value = re.search(rf"pub const {name}: f64 = ([0-9.]+);", rust)
        assert value, f"{name} is not in capture/src/depth_range.rs"
        assert getattr(depth_range, name) == float(value.group(1)), name
