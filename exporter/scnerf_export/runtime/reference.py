"""The full-image reference renderer (PyTorch): 3 source views + target camera -> rgb, depth,
opacity. Deterministic and chunked; a pixel's result does not depend on the chunk it is in."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from .. import cameras as cams
from ..cameras import Camera
from ..config import ModelConfig
from ..model.network import SCNeRF
from ..model.renderer import nearest_heads
from .guided import GuidedPolicy, guided_rendering
from .view import Rendering, pad_images, render_in_passes


@dataclass
class SceneTensors:
    """What the encoder and volume produce for one set of source views: reused by every ray chunk."""

    images: torch.Tensor
    features: torch.Tensor
    volume: torch.Tensor
    intrinsics: torch.Tensor
    extrinsics: torch.Tensor


def source_images(cfg: ModelConfig, images: np.ndarray, background) -> torch.Tensor:
    """Sources (V,H,W,3) in [0,1] -> (V,3,H',W'), padded to the image multiple with the background."""
    padded = pad_images(images.astype(np.float32), cfg.image_multiple, background)
    return torch.from_numpy(np.ascontiguousarray(padded.transpose(0, 3, 1, 2)))


def build_scene(
    model: SCNeRF, images: torch.Tensor, features: torch.Tensor, cameras: list[Camera], near: float, far: float
) -> SceneTensors:
    """The encoded sources with their volume (G2 over the cost volume of [near, far])."""
    volume = model.build_volume(
        features,
        images,
        torch.from_numpy(cams.feature_projections(cameras)),
        torch.from_numpy(cams.depth_planes(near, far, model.cfg.depth_planes)),
    )
    intrinsics = torch.from_numpy(cams.stack_intrinsics(cameras))
    return SceneTensors(images, features, volume, intrinsics, torch.from_numpy(cams.stack_extrinsics(cameras)))


def encode_scene(
    model: SCNeRF, images: np.ndarray, cameras: list[Camera], near: float, far: float, background=(0.0, 0.0, 0.0)
) -> SceneTensors:
    imgs = source_images(model.cfg, images, background)
    return build_scene(model, imgs, model.encode(imgs), cameras, near, far)


def render_rays(
    model: SCNeRF,
    scene: SceneTensors,
    origins: np.ndarray,
    directions: np.ndarray,
    near: float,
    far: float,
    depth_range: tuple[float, float],
    chunk: int,
):
    rgb, depth, opacity = [], [], []
    near_far = torch.tensor([near, far], dtype=torch.float32)
    drange = torch.tensor(depth_range, dtype=torch.float32)
    for start in range(0, origins.shape[0], chunk):
        o = torch.from_numpy(np.ascontiguousarray(origins[start : start + chunk]))
        d = torch.from_numpy(np.ascontiguousarray(directions[start : start + chunk]))
        c, z, a = model.renderer(
            o, d, near_far, drange, scene.volume, scene.images, scene.features, scene.intrinsics, scene.extrinsics
        )
        rgb.append(c)
        depth.append(z)
        opacity.append(a)
    return torch.cat(rgb).numpy(), torch.cat(depth).numpy(), torch.cat(opacity).numpy()


@torch.no_grad()
def render_view(
    model: SCNeRF,
    images: np.ndarray,
    cameras: list[Camera],
    target: Camera,
    near: float,
    far: float,
    background=(0.0, 0.0, 0.0),
    chunk: int = 1024,
) -> Rendering:
    """images: (V,H,W,3) float32 in [0,1] (alpha already composited on ``background``)."""
    model.eval()
    scene = encode_scene(model, images, cameras, near, far, background)
    return render_target(model, scene, target, near, far, background, chunk)


@torch.no_grad()
def render_target(
    model: SCNeRF,
    scene: SceneTensors,
    target: Camera,
    near: float,
    far: float,
    background,
    chunk: int = 1024,
    sampling: str = "full",
) -> Rendering:
    """One target view of an encoded scene, with the paper's S samples per ray (``full``) or by
    guided sampling (``guided``, runtime/guided.py, with the policy ``GuidedPolicy.for_model``)."""
    if sampling == "guided":
        return render_guided_target(model, scene, target, near, far, background, chunk)

    def rays(origins, directions, depth_range):
        return render_rays(model, scene, origins, directions, near, far, depth_range, chunk)

    return render_in_passes(model.cfg, target, near, far, background, rays)


@torch.no_grad()
def render_guided_target(
    model: SCNeRF, scene: SceneTensors, target: Camera, near: float, far: float, background, chunk: int = 1024
) -> Rendering:
    """A view by guided sampling, the PyTorch reference of the server's."""
    near_far = torch.tensor([near, far], dtype=torch.float32)
    r = model.renderer
    tensors = (scene.volume, scene.images, scene.features, scene.intrinsics, scene.extrinsics)
    heads: dict[str, torch.Tensor] = {}

    def guide(origins, directions):
        parts = []
        for start in range(0, origins.shape[0], chunk):
            o, d = (torch.from_numpy(np.ascontiguousarray(a[start : start + chunk])) for a in (origins, directions))
            parts.append(r.guide(o, d, near_far, near_far, *tensors))
        heads.update({name: torch.cat([p.heads[name] for p in parts]) for name in r.rectifiers()})
        return {k: torch.cat([getattr(p, k) for p in parts]).numpy() for k in ("rgb", "depth", "opacity", "weights")}

    def fine(origins, directions, index, multiplicity, guide_rows):
        parts = []
        for start in range(0, origins.shape[0], chunk):
            rows = slice(start, start + chunk)
            o, d, i, m, g = (
                torch.from_numpy(np.ascontiguousarray(a[rows]))
                for a in (origins, directions, index, multiplicity, guide_rows)
            )
            given = {name: nearest_heads(h, g) for name, h in heads.items()}
            parts.append(r.render_samples(o, d, i, m, near_far, near_far, *tensors, given))
        return {k: torch.cat([getattr(p, k) for p in parts]).numpy() for k in ("rgb", "depth", "opacity", "weights")}

    return guided_rendering(GuidedPolicy.for_model(model.cfg), model.cfg, target, background, guide, fine)
