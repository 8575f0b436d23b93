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
