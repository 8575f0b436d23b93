"""What the two Python runtimes (the PyTorch reference and ONNX Runtime) share with each other and
with the server (server/src/pipeline/mod.rs): sources padded to the image multiple, the renderer's
passes over a target view, and the view's outputs."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .. import cameras as cams
from ..cameras import Camera
from ..config import ModelConfig

# (ray origins, ray directions, depth range) -> rgb before the background, depth, opacity
RenderRays = Callable[[np.ndarray, np.ndarray, tuple[float, float]], tuple[np.ndarray, np.ndarray, np.ndarray]]


@dataclass
class Rendering:
    """A rendered view, each output (H, W[, 3])."""

    rgb: np.ndarray  # (H,W,3) composited on the background
    depth: np.ndarray  # (H,W)
    opacity: np.ndarray  # (H,W)
    samples_per_ray: float | None = None  # network samples per pixel (None: the model's S)
    # Guided sampling: how many pixels took each of its paths (runtime/guided.py), else None.
    paths: dict[str, int] | None = None
    # Guided sampling: network samples by stage (``GuidedView.samples_by_stage``), else None.
    samples_by_stage: dict[str, int] | None = None


def pad_images(images: np.ndarray, multiple: int, background) -> np.ndarray:
    """Pad (V,H,W,3) on the right/bottom to a multiple with the background colour; K unchanged."""
    _, h, w, _ = images.shape
    ph, pw = -h % multiple, -w % multiple
    if ph == 0 and pw == 0:
        return images
    out = np.empty((images.shape[0], h + ph, w + pw, 3), dtype=images.dtype)
    out[:] = np.asarray(background, dtype=images.dtype)
    out[:, :h, :w] = images
    return out


def renderer_passes(cfg: ModelConfig) -> int:
    """2 for ``depth_norm: image_minmax``: a depth pass over the whole view gives the depth range that
    normalises the rectifiers' queries in the colour pass (docs/design.md, "Depth normalisation"); else 1.
    mvsnerf's colour head reads no depth range, so it never needs the depth pass."""
    return 2 if cfg.depth_norm == "image_minmax" and cfg.variant != "mvsnerf" else 1


def image_depth_range(depth: np.ndarray, near: float, far: float) -> tuple[float, float]:
    """Min and max of a view's finite depths, or (near, far) if none is finite: the server's rule
    (min_max in server/src/pipeline/mod.rs)."""
    finite = depth[np.isfinite(depth)]
    return (float(finite.min()), float(finite.max())) if finite.size else (near, far)


def render_in_passes(
    cfg: ModelConfig, target: Camera, near: float, far: float, background, render_rays: RenderRays
) -> Rendering:
    """Every pixel of ``target`` through ``render_rays`` in :func:`renderer_passes` passes, composited
    on ``background``."""
    origins, directions = cams.target_rays(target)
    depth_range = (near, far)
    if renderer_passes(cfg) == 2:
        _, depth, _ = render_rays(origins, directions, depth_range)
        depth_range = image_depth_range(depth, near, far)
    rgb, depth, opacity = render_rays(origins, directions, depth_range)
    rgb = rgb + (1.0 - opacity[:, None]) * np.asarray(background, dtype=np.float32)
    shape = (target.height, target.width)
    return Rendering(rgb.reshape(*shape, 3), depth.reshape(shape), opacity.reshape(shape))
