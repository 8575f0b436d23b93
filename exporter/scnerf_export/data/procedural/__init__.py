"""Procedural multi-view training data: textured primitives, exact depth, seeded, no downloads.

Why: the project must train its own SC-NeRF without downloading datasets, and the paper's claim
(rectification helps most when test scenes differ from training: outdoor depth ranges, large
viewpoint gaps) needs scenes whose layout, depth range and source/target gap we control.  Three
layouts mimic DTU (``object``), LLFF (``forward``) and Spaces (``outdoor``); a fourth, ``tabletop``, is
photo-like (textured objects with cast shadows on a table, DTU's framing); see ``layouts``.

Quick use::

    scene = make_scene(seed=0, layout="outdoor")          # 20 views of 160x128, near/far
    src = pick_sources(scene, target_index=5, gap="small")  # 3 nearest views, reference first
    build_dataset("cache/train", n_scenes=96)             # npz per scene; load_scene(path)
    for ex in ProceduralDataset("train", 96, cache_dir="cache/train"): ...

Cameras follow docs/design.md: OpenCV axes, world-to-camera, pixel (u, v) centred at (u, v).
"""

from .core import ALL_LAYOUTS, LAYOUTS, Camera, Scene, View, intrinsics, look_at
from .dataset import (
    TRAIN_SEED0,
    VAL_SEED0,
    Example,
    ProceduralDataset,
    build_dataset,
    load_scene,
    save_preview,
    save_scene,
    scene_filename,
    split_seed,
)
from .geometry import Box, Cylinder, Plane, SkyDome, Sphere
from .raytrace import Haze, Light, World, render_view, trace
from .scenes import GAPS, make_scene, pick_sources, source_ranking
from .textures import Material

__all__ = [
    "ALL_LAYOUTS",
    "GAPS",
    "LAYOUTS",
    "TRAIN_SEED0",
    "VAL_SEED0",
    "Box",
    "Camera",
    "Cylinder",
    "Example",
    "Haze",
    "Light",
    "Material",
    "Plane",
    "ProceduralDataset",
    "Scene",
    "SkyDome",
    "Sphere",
    "View",
    "World",
    "build_dataset",
    "intrinsics",
    "load_scene",
    "look_at",
    "make_scene",
    "pick_sources",
    "render_view",
    "save_preview",
    "save_scene",
    "scene_filename",
    "source_ranking",
    "split_seed",
    "trace",
]
