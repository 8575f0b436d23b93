"""Real scenes for evaluation and validation: a scene folder loaded by its format (DTU's MVSNet
cam.txt, Blender and nerfstudio transforms.json, LLFF poses_bounds.npy, COLMAP text models; one
parser each in :mod:`.dataparsers`), views picked by name or by nearness to a target.

Every scene's cameras are in the canonical form of the project (docs/design.md, "HTTP API"): OpenCV axes
(x right, y down, z forward), world-to-camera, and intrinsics in which the centre of pixel (u, v) is
at image coordinates (u, v). Formats whose convention puts the first pixel's centre at (0.5, 0.5)
(COLMAP, nerfstudio) are shifted by -0.5 in cx, cy.

Image resizing (``scale``) keeps that convention (:meth:`cameras.Camera.resized`: f' = f s and
c' = (c + 0.5) s - 0.5 for the exact ratio s of the new to the old size). LLFF is the one
exception: its principal point is by definition the image centre (W/2, H/2) at whatever
resolution is used, as in LLFF's and MVSNeRF's code.
"""

from __future__ import annotations

from ..cameras import rank_sources
from .dataparsers import PARSERS
from .scene import SceneData, View, natural_key

FORMATS = tuple(PARSERS)


def load_scene(
    path, format: str, scale: float = 1.0, background=None, near=None, far=None, ignore_distortion: bool = False
) -> SceneData:
    """Load a scene folder in one of FORMATS. ``scale`` resizes every image (and its intrinsics);
    ``background`` (RGB in [0,1]) is what alpha is composited on (default white for blender, black
    otherwise); ``near``/``far`` override the format's own depth range (nerfstudio files without
    one and COLMAP models without points3D.txt take it from the poses, ``depth_range``); photos with
    lens distortion are undistorted unless ``ignore_distortion`` (:class:`.dataparsers.base.DataParser`)."""
    fmt = str(format).lower()
    if fmt not in PARSERS:
        raise ValueError(f"unknown scene format {format!r}; expected one of {', '.join(FORMATS)}")
    return PARSERS[fmt].load(
        path, scale=scale, background=background, near=near, far=far, ignore_distortion=ignore_distortion
    )


def nearest_sources(scene: SceneData, target: str, pool: list[str], count: int = 3) -> list[str]:
    """The ``count`` views of ``pool`` nearest the target (:func:`cameras.rank_sources`: camera-centre
    distance, MVSNeRF's evaluation rule), nearest first; the target itself is never a source."""
    candidates = [name for name in pool if name != target]
    ranked = rank_sources(scene.views[target].camera, [scene.views[n].camera for n in candidates])
    if len(ranked) < count:
        raise ValueError(f"view {target!r}: only {len(ranked)} source views face its way, {count} needed")
    return [candidates[i] for i in ranked[:count]]


def get_views(scene: SceneData, names) -> list[View]:
    """Views by name (a list, or a comma-separated string); a clear KeyError for unknown names."""
    if isinstance(names, str):
        names = [n.strip() for n in names.split(",") if n.strip()]
    out = []
    for n in names:
        key = str(n)
        if key not in scene.views:
            avail = ", ".join(sorted(scene.views, key=natural_key))
            raise KeyError(f"view {key!r} is not in the scene; available views: {avail}")
        out.append(scene.views[key])
    return out
