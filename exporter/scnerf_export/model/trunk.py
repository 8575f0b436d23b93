"""M1, the trunk: point features f and E(x) -> radiance features F_r (docs/design.md step 4)."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from ..config import ModelConfig


class TrunkM1(nn.Module):
    """M1: F_r = M1(E(x), f); each layer's output is gated by a per-point Linear(f) before ReLU,
    with E(x) concatenated to the output of layer ``skip_layer`` (reference code's Renderer_ours)."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        e = cfg.position_embedding_channels
        layers = [nn.Linear(e, cfg.width)]
        for i in range(cfg.trunk_layers - 1):
            layers.append(nn.Linear(cfg.width + (e if i == cfg.skip_layer else 0), cfg.width))
        self.linears = nn.ModuleList(layers)
        self.feature_gate = nn.Linear(cfg.point_feature_channels, cfg.width)
        self.skip_layer = cfg.skip_layer

    def forward(self, position_embedding: torch.Tensor, point_features: torch.Tensor) -> torch.Tensor:
        """E(x) (N,E), f (N,F) -> F_r (N,width)."""
        gate = self.feature_gate(point_features)
        h = position_embedding
        for i, layer in enumerate(self.linears):
            pre = self._skip_input_layer(layer, position_embedding, h) if i == self.skip_layer + 1 else layer(h)
            h = F.relu(pre * gate)
        return h

    @staticmethod
    def _skip_input_layer(layer: nn.Linear, position_embedding: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
        """layer([E(x), h]) as the sum of its two halves' products: the same number, without
        writing the concatenation out for every point."""
        e = position_embedding.shape[-1]
        return torch.addmm(F.linear(position_embedding, layer.weight[:, :e], layer.bias), h, layer.weight[:, e:].t())
