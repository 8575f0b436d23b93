"""The geometry and appearance rectifiers: multi-head attention across the sample axis
(docs/design.md steps 5-6)."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from ..config import ModelConfig


class SampleAxisAttention(nn.Module):
    """Multihead(Q, K, V) of paper Eq. (ss) with attention across the sample axis.

    Tokens are the feature channels and each token's embedding is its S values along the ray, so
    the model weighs depth samples rather than feature channels; S is fixed by the weights.
    Q = M3(E(D) ++ E(d)) is one vector per ray (a value per channel token), constant along the
    samples; K = Linear(key features); output = ReLU(V + W_o [head_1 .. head_h]).
    """

    def __init__(self, cfg: ModelConfig, key_channels: int):
        super().__init__()
        query_in = cfg.depth_embedding_channels + cfg.direction_embedding_channels
        inner = cfg.heads * cfg.head_dim
        self.query_m3 = nn.Sequential(nn.Linear(query_in, cfg.width), nn.ReLU(), nn.Linear(cfg.width, cfg.width))
        self.key_embedding = nn.Linear(key_channels, cfg.width)
        self.w_q = nn.Linear(cfg.samples, inner)
        self.w_k = nn.Linear(cfg.samples, inner)
        self.w_v = nn.Linear(cfg.samples, inner)
        self.w_o = nn.Linear(inner, cfg.samples)
        self.heads, self.head_dim = cfg.heads, cfg.head_dim

    def forward(self, query: torch.Tensor, keys: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
        """query (R, Q_in), keys channels first (K_in,R,S), values (R,S,C) -> rectified features (R,S,C)."""
        return self.correct(values, self.summary(query, keys, values))

    def summary(self, query: torch.Tensor, keys: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
        """The heads [head_1 .. head_h] of every ray, (R, h*d_k, C): all that the output at any
        sample reads from the others (output = ReLU(V + W_o heads + b)).

        Computed in the (R, S, C) layout the trunk produces: a projection along S is a left
        product W @ X (R, S, C) -> (R, h*dk, C), so no tensor is transposed. Q is one value per
        channel token, constant along S, so per head Q K^T has inner size 2 instead of d_k:
        (q_c w + b) . k_c' = [q_c, 1] . [w . k_c', b . k_c'], with w the row sums of W_q.
        """
        rays, _, channels = values.shape
        heads, dk = self.heads, self.head_dim
        q_tokens = self.query_m3(query)  # (R,C)
        v_t = (self.w_v.weight @ values).view(rays, heads, dk, channels)  # W_v's bias: see output_bias
        slope_offset = self._key_terms(keys).view(rays, heads, 2, channels)
        q_affine = torch.stack([q_tokens, torch.ones_like(q_tokens)], dim=-1)[:, None]  # (R,1,C,2)
        scores = q_affine @ slope_offset  # (R,h,C,C)
        attention = torch.softmax(scores, dim=-1)
        return (v_t @ attention.transpose(-1, -2)).reshape(rays, heads * dk, channels)

    def output_bias(self) -> torch.Tensor:
        """b of the output, (S): each attention row sums to 1, so W_v's bias comes through the heads
        unchanged and joins W_o's: one broadcast addition instead of two."""
        return self.w_o.weight @ self.w_v.bias + self.w_o.bias

    def correct(
        self, values: torch.Tensor, heads: torch.Tensor, sample_index: torch.Tensor | None = None
    ) -> torch.Tensor:
        """ReLU(V + W_o heads + b) at every sample (``sample_index`` None: values (R,S,C)), or at
        the samples ``sample_index`` (R,K) of the S a ray has (values (R,K,C)): W_o's and b's rows
        are per sample, so K samples read K of them."""
        if sample_index is None:
            return F.relu(values + self.w_o.weight @ heads + self.output_bias()[:, None])
        rows = sample_index.long()
        return F.relu(values + self.w_o.weight[rows] @ heads + self.output_bias()[rows][..., None])

    def _key_terms(self, keys: torch.Tensor) -> torch.Tensor:
        """[w . k_c', b . k_c'] / sqrt(d_k) per head and key token c': (K_in,R,S) -> (R,2h,C).

        K = W_k Linear(keys) enters the scores only through these 2h products, so they are folded
        into W_k first (2h rows along S instead of h d_k), and applied to the K_in key channels
        before the embedding widens them to the C tokens: a sixth to a ninth of the work of K.
        The keys come channels first, as they are sampled, so the rows are one product over all
        channels and rays. The embedding's bias becomes a constant (2h, C) term; W_k's bias adds
        the same amount to every score of a query token, which the softmax cancels, so it is left out.
        """
        heads, dk = self.heads, self.head_dim
        q_parts = torch.stack([self.w_q.weight.sum(dim=1), self.w_q.bias]).view(2, heads, dk).transpose(0, 1)
        q_parts = q_parts / math.sqrt(dk)  # (h,2,dk)
        rows = (q_parts @ self.w_k.weight.view(heads, dk, -1)).reshape(2 * heads, -1)  # (2h,S)
        embedding = self.key_embedding
        bias = rows.sum(dim=1, keepdim=True) * embedding.bias[None, :]  # (2h,C)
        channels, rays, samples = keys.shape
        projected = (keys.reshape(channels * rays, samples) @ rows.transpose(0, 1)).view(channels, -1)
        return F.linear(projected.transpose(0, 1), embedding.weight).view(rays, -1, embedding.out_features) + bias
