"""Pieces several stages share: batch norm with the reference code's statistics, the frequency
encoding E(.), ImageNet normalisation and the affine inverse that ONNX lacks."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from ..config import ModelConfig

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


class BatchStatNorm(nn.Module):
    """Batch norm + leaky ReLU (the reference code's InPlaceABN).

    With ``statistics == "batch"`` it normalises by the statistics of the current batch, which is
    how the public checkpoint was evaluated (three source views for G1, one volume for G2).
    The running statistics are kept so that a checkpoint maps onto the module without leftovers.
    """

    def __init__(self, channels: int, slope: float, eps: float, statistics: str):
        super().__init__()
        self.weight = nn.Parameter(torch.ones(channels))
        self.bias = nn.Parameter(torch.zeros(channels))
        self.register_buffer("running_mean", torch.zeros(channels))
        self.register_buffer("running_var", torch.ones(channels))
        self.register_buffer("num_batches_tracked", torch.tensor(0, dtype=torch.long))
        self.slope = slope
        self.eps = eps
        self.statistics = statistics

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.statistics == "batch" and not torch.compiler.is_exporting():
            # PyTorch's fused kernel: the same numbers, far less memory traffic when training.
            x = F.batch_norm(x, None, None, self.weight, self.bias, training=True, eps=self.eps)
            return F.leaky_relu(x, self.slope)
        if self.statistics == "batch":
            # E[x²] - E[x]²: no full-size tensor of deviations to write (ONNX Runtime's time here
            # is memory traffic). Cancellation costs log2(1 + mean²/var) bits: under 3 in every
            # norm of the public weights' G1 and G2 on real scenes (mean²/var <= 7).
            mean = _mean_over_batch_and_space(x)
            var = _mean_over_batch_and_space(x * x) - mean * mean
            mean, var = mean.reshape(-1).detach(), var.reshape(-1).detach()
        else:
            mean, var = self.running_mean, self.running_var
        # (x - mean) / sqrt(var + eps) * weight + bias as one BatchNormalization operator: one
        # pass over x, where the chain of operators it replaces made four.
        x = F.batch_norm(x, mean, var, self.weight, self.bias, training=False, eps=self.eps)
        return F.leaky_relu(x, self.slope)


def _mean_over_batch_and_space(x: torch.Tensor) -> torch.Tensor:
    """Per-channel mean, one axis at a time: the same value as one big mean, but each partial sum
    stays short, so float32 runtimes that sum naively (ONNX Runtime's ReduceMean) stay accurate
    on volumes of millions of cells."""
    for dim in range(x.dim() - 1, 1, -1):
        x = x.mean(dim=dim, keepdim=True)
    return x.mean(dim=0, keepdim=True)


class ConvNormAct(nn.Module):
    def __init__(self, conv: nn.Module, channels: int, cfg: ModelConfig):
        super().__init__()
        self.conv = conv
        self.bn = BatchStatNorm(channels, cfg.activation_slope, cfg.norm_eps, cfg.norm_statistics)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.bn(self.conv(x))


def frequency_encoding(x: torch.Tensor, freqs: int) -> torch.Tensor:
    """E(x) = [x, sin(2^0 x), ..., sin(2^(L-1) x), cos(2^0 x), ..., cos(2^(L-1) x)].

    The channel order is the reference code's (MVSNeRF models.py, Embedder.embed: all sines,
    then all cosines, the coordinate varying fastest), not the original NeRF's interleaved
    [sin, cos] per frequency: the public checkpoint's first trunk layer and skip layer read the
    63 channels in this order, so any other order scrambles the trunk's input.
    """
    # [2^0 x, ..., 2^(L-1) x] as one product with a block matrix of powers of two: exact, and one
    # operator instead of L multiplications and a concatenation.
    powers = torch.tensor([float(2**i) for i in range(freqs)], dtype=x.dtype, device=x.device)
    scaled = x @ torch.kron(powers[None, :], torch.eye(x.shape[-1], dtype=x.dtype, device=x.device))
    return torch.cat([x, torch.sin(scaled), torch.cos(scaled)], dim=-1)


def normalise_imagenet(images: torch.Tensor) -> torch.Tensor:
    mean = images.new_tensor(IMAGENET_MEAN).view(1, 3, 1, 1)
    std = images.new_tensor(IMAGENET_STD).view(1, 3, 1, 1)
    return (images - mean) / std


def affine_inverse(m: torch.Tensor) -> torch.Tensor:
    """Inverse of 4x4 matrices [[A, b], [0, 1]] via the adjugate of A (ONNX has no Inverse op)."""
    a = m[..., :3, :3]
    r0, r1, r2 = a[..., 0, :], a[..., 1, :], a[..., 2, :]
    cofactor_t = torch.stack(
        [torch.linalg.cross(r1, r2), torch.linalg.cross(r2, r0), torch.linalg.cross(r0, r1)], dim=-1
    )
    det = (r0 * torch.linalg.cross(r1, r2)).sum(-1)
    a_inv = cofactor_t / det[..., None, None]
    b_inv = -(a_inv @ m[..., :3, 3:])
    top = torch.cat([a_inv, b_inv], dim=-1)
    bottom = torch.zeros_like(m[..., 3:, :])
    bottom = torch.cat([bottom[..., :3], torch.ones_like(bottom[..., 3:])], dim=-1)
    return torch.cat([top, bottom], dim=-2)
