"""A capture's depth range from its poses, for files that carry none (nerfstudio and instant-ngp
never do): the twin of the capture crate's ``depth_range::from_poses`` (capture/src/depth_range.rs
says how the margins were set), so that what the exporter reads, and refine trains on, has the
range the server renders the capture with.

The point the optical axes converge on (least squares), and its depth in each camera: near =
``NEAR_MARGIN`` x the smallest; far = ``OBJECT_FAR_MARGIN`` x the largest when the axes spread by
more than ``OBJECT_SPREAD`` (an object seen from around it), else ``FORWARD_FAR_MARGIN`` x the
largest (a forward-facing capture, whose scene reaches far behind the point looked at). Both
sides are held to tests/fixtures/rules/depth_range.json.
"""

from __future__ import annotations

import numpy as np

from ..cameras import Camera

NEAR_MARGIN = 0.4
OBJECT_FAR_MARGIN = 1.6
FORWARD_FAR_MARGIN = 8.0
OBJECT_SPREAD = 0.05
# Below this the axes are (nearly) parallel and meet nowhere in particular (camera.rs, convergence).
MIN_SPREAD = 0.01


def convergence(cameras: list[Camera]) -> tuple[np.ndarray, float] | None:
    """The point nearest to every optical axis, and the axes' spread (the smallest over the largest
    eigenvalue of the least-squares system); None when the axes are nearly parallel or the point is
    in front of no more than half the cameras."""
    a, b = np.zeros((3, 3)), np.zeros(3)
    for c in cameras:
        d = c.forward
        p = np.eye(3) - np.outer(d, d)
        a += p
        b += p @ c.center
    eigen = np.linalg.eigvalsh(a)
    spread = eigen.min() / eigen.max() if eigen.max() > 0 else float("nan")
    if not spread > MIN_SPREAD:
        return None
    point = np.linalg.solve(a, b)
    in_front = sum(float((point - c.center) @ c.forward) > 0 for c in cameras)
    return (point, float(spread)) if in_front * 2 > len(cameras) else None


def from_poses(cameras: list[Camera]) -> tuple[float, float] | None:
    """(near, far) from the cameras' poses; None when they look at no common point in front of them."""
    meet = convergence(cameras)
    if meet is None:
        return None
    point, spread = meet
    depths = [z for c in cameras if (z := float(c.w2c[2, :3] @ point + c.w2c[2, 3])) > 0]
    if not depths:
        return None
    far_margin = OBJECT_FAR_MARGIN if spread > OBJECT_SPREAD else FORWARD_FAR_MARGIN
    return NEAR_MARGIN * min(depths), far_margin * max(depths)


def resolve(near: float | None, far: float | None, from_file, cameras: list[Camera], source: str):
    """``near``/``far`` from the arguments, else from the file (``from_file``: (near, far), either
    None), else both from the poses; a ValueError naming ``source`` when none gives one."""
    near = from_file[0] if near is None else near
    far = from_file[1] if far is None else far
    if near is None or far is None:
        poses = from_poses(cameras)
        if poses is None:
            raise ValueError(
                f"{source}: no near/far in the file, and the poses do not give one (the cameras look at no "
                "common point in front of them); pass them explicitly (--near/--far)"
            )
        near = poses[0] if near is None else near
        far = poses[1] if far is None else far
    return near, far
