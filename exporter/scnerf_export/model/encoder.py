"""G1, the image encoder (docs/design.md step 1)."""

from __future__ import annotations

import torch
from torch import nn

from ..config import ModelConfig
from .layers import ConvNormAct, normalise_imagenet


class EncoderG1(nn.Module):
    """G1: F_i = G1(I_i), (3,H,W) -> (C1,H/4,W/4); three Conv-BN-act stages, 1x1 output conv."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        c0, c1, c2 = cfg.encoder_channels

        def block(cin: int, cout: int, k: int, stride: int) -> ConvNormAct:
            conv = nn.Conv2d(cin, cout, k, stride=stride, padding=k // 2, bias=False)
            return ConvNormAct(conv, cout, cfg)

        self.conv0 = nn.Sequential(block(3, c0, 3, 1), block(c0, c0, 3, 1))
        self.conv1 = nn.Sequential(block(c0, c1, 5, 2), block(c1, c1, 3, 1), block(c1, c1, 3, 1))
        self.conv2 = nn.Sequential(block(c1, c2, 5, 2), block(c2, c2, 3, 1), block(c2, c2, 3, 1))
        self.toplayer = nn.Conv2d(c2, cfg.feature_channels, 1)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """images: (V,3,H,W) in [0,1] -> features (V,C1,H/4,W/4)."""
        x = normalise_imagenet(images)
        return self.toplayer(self.conv2(self.conv1(self.conv0(x))))
