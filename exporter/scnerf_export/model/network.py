"""SC-NeRF, the whole network: G1, cost volume + G2, and the per-ray renderer."""

from __future__ import annotations

import torch
from torch import nn

from ..config import ModelConfig
from .cost_volume import VolumeNetG2, build_cost_volume
from .encoder import EncoderG1
from .renderer import RayRenderer


class SCNeRF(nn.Module):
    """The whole network; the three ONNX sub-graphs are its encoder, volume and renderer."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.cfg = cfg
        self.encoder = EncoderG1(cfg)
        self.volume_net = VolumeNetG2(cfg)
        self.renderer = RayRenderer(cfg)

    def encode(self, images: torch.Tensor) -> torch.Tensor:
        return self.encoder(images)

    def build_volume(
        self, features: torch.Tensor, images: torch.Tensor, projections: torch.Tensor, depth_planes: torch.Tensor
    ) -> torch.Tensor:
        cost = build_cost_volume(features, images, projections, depth_planes, self.cfg.pad)
        return self.volume_net(cost)

    def volume_slab(
        self,
        features: torch.Tensor,
        images: torch.Tensor,
        projections: torch.Tensor,
        depth_planes: torch.Tensor,
        plane_inside: torch.Tensor,
    ) -> torch.Tensor:
        """G2's first convolution over the cost volume of a slab of planes (``depth_planes``: the
        slab with one plane of halo each side; ``plane_inside``: which of them lie inside the
        volume, see ``cost_volume.slab_halo``). The cost
        volume's variance is per plane, so the slabs together give exactly ``build_volume``'s
        first convolution, while only one slab's warped features exist at a time."""
        cost = build_cost_volume(features, images, projections, depth_planes, self.cfg.pad)
        return self.volume_net.first_conv_of_slab(cost * plane_inside.view(1, 1, -1, 1, 1))

    def volume_from_slabs(self, conv0: torch.Tensor) -> torch.Tensor:
        """The encoding volume from the slabs' first convolution, concatenated over the planes."""
        return self.volume_net.from_first_conv(conv0)
