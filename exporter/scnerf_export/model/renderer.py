"""The renderer graph: per target ray, its S points through M1, M2, compositing, the rectifiers
and M4 (docs/design.md steps 4-7).

Data path per ray: points x -> point features f = [s, colours, masks] -> M1 -> F_r -> M2 -> sigma
-> rendered depth D -> geometry rectification (F_r -> F_c) -> appearance rectification
(F_c -> F) -> M4 -> colour c -> compositing.

Every function of the model package is traced into the ONNX sub-graphs, so it avoids
data-dependent Python control flow and ops without an ONNX equivalent (cumprod, linalg.inv).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import nn

from ..config import ModelConfig
from .colour import ColourHeadM4, ColourHeadMVSNeRF
from .layers import frequency_encoding
from .points import reference_frustum_coordinates, sample_views, sample_volume
from .rectifiers import SampleAxisAttention
from .trunk import TrunkM1


def composite_weights(sigma: torch.Tensor) -> torch.Tensor:
    """w_k = alpha_k T_k with alpha_k = 1 - exp(-sigma_k) and T_k = prod_{j<k} (1 - alpha_j)
    (paper Eq. 11-12), written with an exclusive cumulative sum because cumprod has no ONNX op;
    the 1e-10 matches the reference code."""
    alpha = 1.0 - torch.exp(-sigma)
    log_transmit = torch.cumsum(torch.log(1.0 - alpha + 1e-10), dim=-1)
    exclusive = torch.cat([torch.zeros_like(log_transmit[:, :1]), log_transmit[:, :-1]], dim=-1)
    return alpha * torch.exp(exclusive)


class RadiancePoints(NamedTuple):
    """A chunk of rays after the trunk: everything the heads read, channels first where sampled."""

    z: torch.Tensor  # sample depths along the target's axis, (S) shared by every ray or (R,S)
    radiance: torch.Tensor  # F_r (R*S, width)
    point_features: torch.Tensor  # f (8+4V, R*S)
    appearance: torch.Tensor | None  # mean [F_i, I_i] over the views (C1+3, R*S)
    ref_dir: torch.Tensor  # unit ray directions in the reference camera's frame (R,3)


class RayRenderer(nn.Module):
    """Everything per target ray: point features, M1, M2, rectification, M4, compositing."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.cfg = cfg
        self.m1 = TrunkM1(cfg)
        if cfg.variant == "mvsnerf":
            self.m2 = nn.Sequential(nn.Linear(cfg.width, 1), nn.ReLU())
            self.colour_head = ColourHeadMVSNeRF(cfg)
        else:
            self.m2 = nn.Sequential(nn.Linear(cfg.width, cfg.width), nn.ReLU(), nn.Linear(cfg.width, 1), nn.ReLU())
            self.colour_head = ColourHeadM4(cfg)
        self.geometry = SampleAxisAttention(cfg, cfg.point_feature_channels) if cfg.geometry_rectification else None
        self.appearance = SampleAxisAttention(cfg, cfg.feature_channels + 3) if cfg.appearance_rectification else None

    def forward(
        self,
        ray_origins: torch.Tensor,
        ray_directions: torch.Tensor,
        near_far: torch.Tensor,
        depth_range: torch.Tensor,
        volume: torch.Tensor,
        images: torch.Tensor,
        features: torch.Tensor,
        intrinsics: torch.Tensor,
        extrinsics: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Returns rgb (R,3) before background compositing, depth (R), opacity (R)."""
        points = self.radiance_points(
            ray_origins, ray_directions, near_far, volume, images, features, intrinsics, extrinsics
        )
        return self.shade(points, depth_range)

    def radiance_points(
        self,
        ray_origins: torch.Tensor,
        ray_directions: torch.Tensor,
        near_far: torch.Tensor,
        volume: torch.Tensor,
        images: torch.Tensor,
        features: torch.Tensor | None,
        intrinsics: torch.Tensor,
        extrinsics: torch.Tensor,
    ) -> RadiancePoints:
        """The S points of every ray through M1: what the heads (M2, rectifiers, M4) read."""
        cfg = self.cfg
        samples = cfg.samples
        _, _, height, width = images.shape
        steps = torch.linspace(0.0, 1.0, samples, dtype=ray_origins.dtype, device=ray_origins.device)
        z = near_far[0] * (1.0 - steps) + near_far[1] * steps  # (S) target z-depths
        points = (ray_origins[:, None, :] + ray_directions[:, None, :] * z[None, :, None]).reshape(-1, 3)

        frustum = reference_frustum_coordinates(points, intrinsics[0], extrinsics[0], near_far, height, width, cfg.pad)
        s = sample_volume(volume, frustum)
        colours, appearance = sample_views(
            points, images, features if self.appearance is not None else None, intrinsics, extrinsics
        )
        point_features = torch.cat([s, colours])  # f, channels first (8+4V, N)

        unit_dir = ray_directions / torch.linalg.vector_norm(ray_directions, dim=-1, keepdim=True)
        ref_dir = unit_dir @ extrinsics[0, :3, :3].transpose(0, 1)  # d in the reference frame
        radiance = self.m1(frequency_encoding(frustum, cfg.position_freqs), point_features.transpose(0, 1))
        return RadiancePoints(z, radiance, point_features, appearance, ref_dir)

    def shade(
        self, points: RadiancePoints, depth_range: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """M2 -> compositing weights and depth D -> rectification -> M4 -> rgb (R,3), depth, opacity.

        depth_range is (2) for the whole chunk, or (2,R) per ray (training batches mix scenes)."""
        cfg = self.cfg
        rays, samples = points.ref_dir.shape[0], cfg.samples
        ref_dir, z = points.ref_dir, points.z
        sigma = self.m2(points.radiance).view(rays, samples)
        weights = composite_weights(sigma)
        depth = (weights * (z[None, :] if z.dim() == 1 else z)).sum(dim=-1)
        opacity = weights.sum(dim=-1)

        radiance = points.radiance.view(rays, samples, -1)
        if cfg.variant == "mvsnerf":
            dirs = ref_dir[:, None, :].expand(-1, samples, -1)
            colour = self.colour_head(radiance, dirs)
        else:
            # Clamped: an image_minmax range of a flat depth image has max == min.
            span = torch.clamp(depth_range[1] - depth_range[0], min=1e-6)
            depth_norm = ((depth - depth_range[0]) / span)[:, None]
            depth_embedding = frequency_encoding(depth_norm, cfg.depth_freqs)
            direction_embedding = frequency_encoding(ref_dir, cfg.direction_freqs)
            query = torch.cat([depth_embedding, direction_embedding], dim=-1)
            if self.geometry is not None:  # F_c = Multihead(Q, K = f, V = F_r)
                radiance = self.geometry(query, points.point_features.view(-1, rays, samples), radiance)
            if self.appearance is not None:  # F = Multihead(Q, K = mean F_a, V = F_c)
                radiance = self.appearance(query, points.appearance.view(-1, rays, samples), radiance)
            colour = self.colour_head(radiance, query)
        rgb = (weights[..., None] * colour).sum(dim=1)
        return rgb, depth, opacity
