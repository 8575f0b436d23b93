"""Synthetic camera rigs, textured images and random-weight networks: the exporter's tracing and
validation inputs, the parity fixtures' scenes, and the tests'. Production code may import this
module: it depends only on the cameras, the config and the network."""

from __future__ import annotations

import numpy as np
import torch

from . import cameras as cams
from .cameras import Camera
from .config import ModelConfig
from .model.network import SCNeRF


def smooth_pattern(rng: np.random.Generator, height: int, width: int) -> np.ndarray:
    """A textured [0,1] image: a few random sinusoids per channel (bilinear sampling matters)."""
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    img = np.zeros((height, width, 3))
    for c in range(3):
        for _ in range(4):
            fu, fv = rng.uniform(-0.25, 0.25, size=2)
            img[..., c] += np.sin(fu * u + fv * v + rng.uniform(0, 2 * np.pi))
    img = (img - img.min()) / (img.max() - img.min())
    return img.astype(np.float32)


def rig_cameras(height: int, width: int, radius: float = 3.0) -> tuple[list[Camera], Camera, float, float]:
    """Three sources and a target around the origin, like a small DTU rig."""
    K = cams.pinhole(1.2 * width, width, height)
    eyes = [(0.0, 0.0, -radius), (0.5, 0.1, -radius), (-0.3, 0.4, -radius), (0.15, 0.2, -radius)]
    all_cams = [Camera(K, cams.look_at(e, (0.0, 0.0, 0.0), up=(0.0, -1.0, 0.0)), width, height) for e in eyes]
    return all_cams[:3], all_cams[3], radius - 1.0, radius + 1.0


def synthetic_rig(cfg: ModelConfig, height: int, width: int, seed: int = 0) -> dict[str, torch.Tensor]:
    """Tensors for tracing and validating the graphs."""
    rng = np.random.default_rng(seed)
    sources, target, near, far = rig_cameras(height, width)
    images = np.stack([smooth_pattern(rng, height, width) for _ in sources]).transpose(0, 3, 1, 2)
    origins, directions = cams.target_rays(target)
    t = torch.from_numpy
    return {
        "images": t(np.ascontiguousarray(images)),
        "projections": t(cams.feature_projections(sources)),
        "depth_planes": t(cams.depth_planes(near, far, cfg.depth_planes)),
        "intrinsics": t(cams.stack_intrinsics(sources)),
        "extrinsics": t(cams.stack_extrinsics(sources)),
        "near_far": torch.tensor([near, far], dtype=torch.float32),
        "ray_origins": t(origins),
        "ray_directions": t(directions),
    }


def random_model(cfg: ModelConfig, seed: int) -> SCNeRF:
    """Random weights whose renders are not degenerate: density biased so opacity is mid-range."""
    torch.manual_seed(seed)
    model = SCNeRF(cfg)
    with torch.no_grad():
        density_out = model.renderer.m2[-2]
        density_out.bias.fill_(0.05)
    return model.eval()
