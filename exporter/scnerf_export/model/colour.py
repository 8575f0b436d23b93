"""Colour heads: M4 (SC-NeRF, docs/design.md step 7) and MVSNeRF's."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from ..config import ModelConfig


class ColourHeadMVSNeRF(nn.Module):
    """Baseline colour head: c = sigmoid(L(ReLU(L([L(F_r), d]))))."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.feature_linear = nn.Linear(cfg.width, cfg.width)
        self.hidden = nn.Linear(cfg.width + 3, cfg.colour_hidden)
        self.out = nn.Linear(cfg.colour_hidden, 3)

    def forward(self, radiance: torch.Tensor, direction: torch.Tensor) -> torch.Tensor:
        h = torch.cat([self.feature_linear(radiance), direction], dim=-1)
        return torch.sigmoid(self.out(F.relu(self.hidden(h))))


class ColourHeadM4(nn.Module):
    """M4: c = sigmoid(MLP(F, E(D), E(d)))."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        cin = cfg.width + cfg.depth_embedding_channels + cfg.direction_embedding_channels
        self.hidden = nn.Linear(cin, cfg.colour_hidden)
        self.out = nn.Linear(cfg.colour_hidden, 3)

    def forward(self, features: torch.Tensor, ray_embedding: torch.Tensor) -> torch.Tensor:
        """features F (R,S,C), ray_embedding [E(D), E(d)] (R,E) -> colours (R,S,3).

        The first layer reads [F, E(D), E(d)]; the embeddings are one per ray, so their part of it
        is computed per ray and broadcast along S instead of copied to every sample.
        """
        c = features.shape[-1]
        per_ray = F.linear(ray_embedding, self.hidden.weight[:, c:], self.hidden.bias)
        h = F.linear(features, self.hidden.weight[:, :c]) + per_ray[:, None, :]
        return torch.sigmoid(self.out(F.relu(h)))
