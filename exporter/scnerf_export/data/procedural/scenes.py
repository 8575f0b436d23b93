"""Rendering whole scenes and choosing source views for a target."""

from __future__ import annotations

from ...cameras import Camera, rank_sources
from .core import Scene
from .layouts import build_layout
from .raytrace import render_view

GAPS: tuple[str, ...] = ("small", "medium", "large")


def make_scene(
    seed: int, layout: str, n_views: int = 20, width: int = 160, height: int = 128, supersample: int = 2
) -> Scene:
    """Render ``n_views`` views of procedural scene ``seed`` in ``layout``.

    Deterministic: the same arguments give bit-identical arrays (on another CPU or numpy build,
    SIMD maths may change the last bit of a few values; the npz cache pins a rendering down).  ``supersample`` = 2
    anti-aliases rgb/alpha with 2x2 sub-pixel rays (procedural textures alias badly otherwise, which
    would make colours inconsistent between views); depth always comes from the pixel-centre ray.
    """
    world, cameras, near, far = build_layout(seed, layout, n_views, width, height)
    views = [render_view(world, cam, supersample=supersample) for cam in cameras]
    return Scene(views=views, near=near, far=far, layout=layout, seed=int(seed), meta={"supersample": int(supersample)})


def source_ranking(scene: Scene, target_index: int) -> list[int]:
    """All other views that face the target's way, nearest camera centre first."""
    return camera_ranking([v.camera for v in scene.views], target_index)


def camera_ranking(cameras: list[Camera], target_index: int) -> list[int]:
    """All other cameras that face the target's way, nearest centre first
    (:func:`scnerf_export.cameras.rank_sources`)."""
    others = [i for i in range(len(cameras)) if i != target_index]
    ranked = rank_sources(cameras[target_index], [cameras[i] for i in others])
    return [others[i] for i in ranked]


def pick_sources(scene: Scene, target_index: int, gap: str = "small", n_sources: int = 3) -> list[int]:
    """Indices of the source views for a target (:func:`pick_camera_sources` on the scene's cameras)."""
    return pick_camera_sources([v.camera for v in scene.views], target_index, gap, n_sources)


def pick_camera_sources(cameras: list[Camera], target_index: int, gap: str = "small", n_sources: int = 3) -> list[int]:
    """Indices of the source cameras for a target, nearest first (the first is the reference view).
    Ranking needs the cameras only, so sources are picked before anything is rendered.

    Other views are ranked by the distance of their camera centre to the target's (as MVSNeRF does
    for LLFF; for the object layout, where cameras sit at one radius, this is the same ranking as by
    viewing angle).  The viewpoint-gap setting, modelled on the paper's Spaces protocol (sources
    progressively farther from the target), takes consecutive windows of that ranking:

    * ``small``  : ranks [0, n)     - the n nearest views (the paper's / MVSNeRF's default)
    * ``medium`` : ranks [n, 2n)
    * ``large``  : ranks [2n, 3n)

    With n = 3 that is ranks 0-2, 3-5, 6-8, so a scene needs at least 3n + 1 = 10 views for all three
    settings.  If a scene has too few views the window slides back to the farthest n views.
    """
    if gap not in GAPS:
        raise ValueError(f"gap must be one of {GAPS}, got {gap!r}")
    ranking = camera_ranking(cameras, target_index)
    if len(ranking) < n_sources:
        raise ValueError(f"scene has {len(cameras)} views; need at least {n_sources + 1}")
    start = min(GAPS.index(gap) * n_sources, len(ranking) - n_sources)
    return ranking[start : start + n_sources]
