"""Data types and camera maths shared by the procedural generator.

Conventions (the same as docs/design.md and the server):

* OpenCV camera axes: x right, y down, z forward.  ``w2c`` maps world points to camera points.
* Intrinsics put the *centre* of pixel (u, v) at image coordinates (u, v).  The ray of pixel (u, v)
  therefore has the camera-frame direction ``[(u - cx) / fx, (v - cy) / fy, 1]`` and the image centre
  is at ``((W - 1) / 2, (H - 1) / 2)``.
* Because that direction has z = 1, the ray parameter t of a hit *is* its z-depth in the camera
  frame; the renderer relies on this and never normalises the ray direction it intersects with.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ...cameras import Camera, look_at, pinhole

# The three scene families of the procedural training mix (object: DTU-like, forward: LLFF-like,
# outdoor: Spaces-like), and the photo-like tabletop (DTU's framing at DTU's resolution).
LAYOUTS: tuple[str, ...] = ("object", "forward", "outdoor")
ALL_LAYOUTS: tuple[str, ...] = LAYOUTS + ("tabletop",)


@dataclass
class View:
    """One rendered image.

    ``image`` (H, W, 3) float32 in [0, 1], quantised to multiples of 1/255 like an 8-bit photo, so a
    scene reloaded from the npz cache is bit-identical to a freshly rendered one.
    ``depth`` (H, W) float32: z-depth in the camera frame of the ray through the pixel centre;
    ``+inf`` where that ray hits nothing (only possible in the ``object`` layout).
    ``alpha`` (H, W) float32 in [0, 1]: fraction of the pixel's sub-samples that hit a surface
    (fractional on silhouettes when rendered with supersampling); the sky dome of ``outdoor`` counts
    as a surface, so outdoor views are opaque everywhere.  Pixels with alpha 0 are black, which is
    what the network's compositing (rgb = sum w c, no background term) produces for empty space.
    """

    image: np.ndarray
    depth: np.ndarray
    alpha: np.ndarray
    camera: Camera


@dataclass
class Scene:
    """A set of views of one procedural scene with the [near, far] that brackets all its depths."""

    views: list[View]
    near: float
    far: float
    layout: str
    seed: int
    meta: dict = field(default_factory=dict)


def intrinsics(width: int, height: int, hfov_deg: float) -> np.ndarray:
    """K (3, 3) with square pixels, the given horizontal field of view and a centred principal point.

    The field of view, not the focal length in pixels, is the scene parameter, so the same seed renders
    the same picture at any resolution.
    """
    return pinhole(width / (2.0 * np.tan(np.radians(hfov_deg) / 2.0)), width, height)


def yaw_pitch_w2c(eye: np.ndarray, yaw: float, pitch: float) -> np.ndarray:
    """World-to-camera matrix for a level camera looking along +y, turned by ``yaw`` (radians, to the
    left is positive) and tilted by ``pitch`` (radians, up is positive)."""
    direction = np.array([-np.sin(yaw) * np.cos(pitch), np.cos(yaw) * np.cos(pitch), np.sin(pitch)])
    return look_at(eye, np.asarray(eye, dtype=np.float64) + direction)
