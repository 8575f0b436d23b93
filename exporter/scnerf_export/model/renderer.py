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


class Shading(NamedTuple):
    """What the heads make of a chunk of rays: the pixel's outputs and what guided sampling reads."""

    rgb: torch.Tensor  # (R,3) before background compositing
    depth: torch.Tensor  # (R)
    opacity: torch.Tensor  # (R)
    weights: torch.Tensor  # compositing weights w_k, (R,K)
    heads: dict[str, torch.Tensor]  # per rectifier, the heads its outputs read (R, h*d_k, C)


def uniform_depths(near_far: torch.Tensor, samples: int) -> torch.Tensor:
    """The paper's S sample depths, uniform in [near, far]: (S)."""
    steps = torch.linspace(0.0, 1.0, samples, dtype=near_far.dtype, device=near_far.device)
    return near_far[0] * (1.0 - steps) + near_far[1] * steps


def nearest_heads(grid: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """Each ray's heads, those of the nearest ray rendered in full: ``grid`` (G, h*d_k, C), ``index``
    (R) rows of it (integers held as float32) -> (R, h*d_k, C)."""
    return grid[index.long()]


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

    def rectifiers(self) -> dict[str, SampleAxisAttention]:
        """The rectifiers of this variant, in the order they run: geometry first (the paper's best)."""
        found = {"geometry": self.geometry, "appearance": self.appearance}
        return {name: r for name, r in found.items() if r is not None}

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

    def guide(
        self,
        ray_origins: torch.Tensor,
        ray_directions: torch.Tensor,
        near_far: torch.Tensor,
        depth_range: torch.Tensor,
        volume: torch.Tensor,
        images: torch.Tensor,
        features: torch.Tensor | None,
        intrinsics: torch.Tensor,
        extrinsics: torch.Tensor,
    ) -> Shading:
        """``forward`` at the S uniform samples, also returning each ray's compositing weights and
        rectifier heads: what guided sampling places and rectifies other rays' samples with."""
        points = self.radiance_points(
            ray_origins, ray_directions, near_far, volume, images, features, intrinsics, extrinsics
        )
        return self.shade_guided(points, depth_range, torch.ones_like(points.z), None)

    def render_samples(
        self,
        ray_origins: torch.Tensor,
        ray_directions: torch.Tensor,
        sample_index: torch.Tensor,
        multiplicity: torch.Tensor,
        near_far: torch.Tensor,
        depth_range: torch.Tensor,
        volume: torch.Tensor,
        images: torch.Tensor,
        features: torch.Tensor | None,
        intrinsics: torch.Tensor,
        extrinsics: torch.Tensor,
        heads: dict[str, torch.Tensor],
    ) -> Shading:
        """K of a ray's S uniform samples (``sample_index`` (R,K), increasing): the network at
        those alone. Each stands for ``multiplicity`` (R,K) uniform samples, so its opacity is
        1 - exp(-m sigma) (the compositing's quadrature over the samples it stands for); the
        rectifiers read ``heads`` given per ray (:func:`nearest_heads`) instead of computing
        them from all S samples."""
        step = (near_far[1] - near_far[0]) / (self.cfg.samples - 1)
        z = near_far[0] + sample_index * step
        points = self.radiance_points(
            ray_origins, ray_directions, near_far, volume, images, features, intrinsics, extrinsics, z
        )
        return self.shade_guided(points, depth_range, multiplicity, (sample_index, heads))

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
        z: torch.Tensor | None = None,
    ) -> RadiancePoints:
        """The points of every ray through M1: what the heads (M2, rectifiers, M4) read. ``z``: the
        target z-depths of the points, (R,K) per ray, or by default the S uniform ones."""
        cfg = self.cfg
        _, _, height, width = images.shape
        if z is None:
            z = uniform_depths(near_far, cfg.samples)  # (S) target z-depths
        along = z[None, :, None] if z.dim() == 1 else z[:, :, None]
        points = (ray_origins[:, None, :] + ray_directions[:, None, :] * along).reshape(-1, 3)

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
        rays, samples = points.ref_dir.shape[0], self.cfg.samples
        sigma = self.m2(points.radiance).view(rays, samples)
        weights = composite_weights(sigma)
        depth, opacity = self._depth_and_opacity(points.z, weights)
        radiance = points.radiance.view(rays, samples, -1)
        query = self._query(depth, depth_range, points.ref_dir)
        for name, rectifier in self.rectifiers().items():  # F_c = Multihead(Q, f, F_r); F = Multihead(Q, F_a, F_c)
            radiance = rectifier(query, self._keys(points, name, rays, samples), radiance)
        return self._composite(radiance, query, points.ref_dir, weights), depth, opacity

    def shade_guided(
        self,
        points: RadiancePoints,
        depth_range: torch.Tensor,
        multiplicity: torch.Tensor,
        given: tuple[torch.Tensor, dict[str, torch.Tensor]] | None,
    ) -> Shading:
        """``shade`` for guided sampling: compositing weights with each sample's ``multiplicity``;
        the rectifiers' heads computed here from all S samples (``given`` None: a guide ray), or
        given with the samples' indices for rays of K samples."""
        rays = points.ref_dir.shape[0]
        samples = points.radiance.shape[0] // rays
        sigma = self.m2(points.radiance).view(rays, samples)
        weights = composite_weights(sigma * multiplicity)
        depth, opacity = self._depth_and_opacity(points.z, weights)
        radiance = points.radiance.view(rays, samples, -1)
        query = self._query(depth, depth_range, points.ref_dir)
        heads = {}
        for name, rectifier in self.rectifiers().items():
            if given is None:
                heads[name] = rectifier.summary(query, self._keys(points, name, rays, samples), radiance)
                radiance = rectifier.correct(radiance, heads[name])
            else:
                radiance = rectifier.correct(radiance, given[1][name], given[0])
        rgb = self._composite(radiance, query, points.ref_dir, weights)
        return Shading(rgb, depth, opacity, weights, heads)

    @staticmethod
    def _depth_and_opacity(z: torch.Tensor, weights: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """D = sum_k w_k z_k and the opacity sum_k w_k."""
        return (weights * (z[None, :] if z.dim() == 1 else z)).sum(dim=-1), weights.sum(dim=-1)

    def _query(self, depth: torch.Tensor, depth_range: torch.Tensor, ref_dir: torch.Tensor) -> torch.Tensor | None:
        """[E(D), E(d)]: the rectifiers' query and M4's ray input (None for mvsnerf)."""
        cfg = self.cfg
        if cfg.variant == "mvsnerf":
            return None
        # Clamped: an image_minmax range of a flat depth image has max == min.
        span = torch.clamp(depth_range[1] - depth_range[0], min=1e-6)
        depth_norm = ((depth - depth_range[0]) / span)[:, None]
        depth_embedding = frequency_encoding(depth_norm, cfg.depth_freqs)
        direction_embedding = frequency_encoding(ref_dir, cfg.direction_freqs)
        return torch.cat([depth_embedding, direction_embedding], dim=-1)

    @staticmethod
    def _keys(points: RadiancePoints, rectifier: str, rays: int, samples: int) -> torch.Tensor:
        """A rectifier's keys, channels first (K_in,R,S): f for geometry, F_a for appearance."""
        keys = points.point_features if rectifier == "geometry" else points.appearance
        return keys.view(-1, rays, samples)

    def _composite(
        self, radiance: torch.Tensor, query: torch.Tensor | None, ref_dir: torch.Tensor, weights: torch.Tensor
    ) -> torch.Tensor:
        """M4 (or MVSNeRF's colour head) per sample, composited: rgb (R,3)."""
        if query is None:
            dirs = ref_dir[:, None, :].expand(-1, radiance.shape[1], -1)
            colour = self.colour_head(radiance, dirs)
        else:
            colour = self.colour_head(radiance, query)
        return (weights[..., None] * colour).sum(dim=1)
