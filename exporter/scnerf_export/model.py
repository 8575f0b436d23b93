"""SC-NeRF (and its MVSNeRF baseline) in PyTorch, following the paper's symbols.

Data path: images -> G1 -> features F_i -> cost volume P -> G2 -> encoding volume V;
per target ray: points x -> point features f = [s, colours, masks] -> M1 -> F_r -> M2 -> sigma
-> rendered depth D -> geometry rectification (F_r -> F_c) -> appearance rectification
(F_c -> F) -> M4 -> colour c -> compositing.

Every function here is traced into the ONNX sub-graphs, so it avoids data-dependent Python
control flow and ops without an ONNX equivalent (cumprod, linalg.inv).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import nn

from .config import ModelConfig

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


# ---------------------------------------------------------------------------------------------
# Shared pieces
# ---------------------------------------------------------------------------------------------


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
        shape = (1, -1) + (1,) * (x.dim() - 2)
        if self.statistics == "batch":
            mean = _mean_over_batch_and_space(x)
            var = _mean_over_batch_and_space((x - mean).square())
        else:
            mean, var = self.running_mean.view(shape), self.running_var.view(shape)
        x = (x - mean) * torch.rsqrt(var + self.eps) * self.weight.view(shape) + self.bias.view(shape)
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


# ---------------------------------------------------------------------------------------------
# G1: image encoder
# ---------------------------------------------------------------------------------------------


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


# ---------------------------------------------------------------------------------------------
# Cost volume P and G2
# ---------------------------------------------------------------------------------------------


def plane_sweep_grid(
    projections: torch.Tensor, depth_planes: torch.Tensor, h: int, w: int, pad: int
) -> torch.Tensor:
    """Sampling grids of the homographies H_i(z) for every source view (paper Eq. 2).

    projections: (V,4,4) feature-resolution K[R|t]; view 0 is the reference.
    Returns (V-1, D, Hp*Wp, 2) grids in grid_sample's [-1,1] coordinates (align_corners=True).
    """
    ref_inverse = affine_inverse(projections[0])
    relative = projections[1:] @ ref_inverse  # source pixel*depth from reference pixel*depth
    rot, trans = relative[:, :3, :3], relative[:, :3, 3:]
    hp, wp = h + 2 * pad, w + 2 * pad
    ys = torch.arange(hp, dtype=projections.dtype, device=projections.device) - pad
    xs = torch.arange(wp, dtype=projections.dtype, device=projections.device) - pad
    gy, gx = torch.meshgrid(ys, xs, indexing="ij")
    pixels = torch.stack([gx.reshape(-1), gy.reshape(-1), torch.ones_like(gx).reshape(-1)])  # (3,P)
    rotated = rot @ pixels  # (V-1,3,P)
    points = rotated[:, None] + trans[:, None] / depth_planes.view(1, -1, 1, 1)  # (V-1,D,3,P)
    u = points[:, :, 0] / points[:, :, 2] / ((w - 1) / 2.0) - 1.0
    v = points[:, :, 1] / points[:, :, 2] / ((h - 1) / 2.0) - 1.0
    return torch.stack([u, v], dim=-1)


def build_cost_volume(
    features: torch.Tensor,
    images: torch.Tensor,
    projections: torch.Tensor,
    depth_planes: torch.Tensor,
    pad: int,
) -> torch.Tensor:
    """P = [images of every view warped to the planes (3V), Var_i(F_{i,z})] (paper Eq. 3-4).

    Reproduces the reference code: the variance counts the reference view everywhere (its padded
    border holds zeros) plus each source view where its warp lands inside the image.
    """
    views, _, h, w = features.shape
    d = depth_planes.shape[0]
    hp, wp = h + 2 * pad, w + 2 * pad
    small = F.interpolate(normalise_imagenet(images), size=(h, w), mode="bilinear", align_corners=False)
    grids = plane_sweep_grid(projections, depth_planes, h, w, pad)  # (V-1,D,P,2)

    ref_features = F.pad(features[:1], (pad, pad, pad, pad))[:, :, None].expand(-1, -1, d, -1, -1)
    ref_image = F.pad(small[:1], (pad, pad, pad, pad))[:, :, None].expand(-1, -1, d, -1, -1)
    volume_sum = ref_features
    volume_sq_sum = ref_features.square()
    count = torch.ones_like(ref_features[:, :1])
    warped_images = [ref_image]
    for i in range(1, views):
        grid = grids[i - 1 : i]
        warped = F.grid_sample(features[i : i + 1], grid, mode="bilinear", padding_mode="zeros",
                               align_corners=True).view(1, -1, d, hp, wp)
        warped_img = F.grid_sample(small[i : i + 1], grid, mode="bilinear", padding_mode="zeros",
                                   align_corners=True).view(1, -1, d, hp, wp)
        inside = ((grid > -1.0) & (grid < 1.0)).all(dim=-1).to(features.dtype).view(1, 1, d, hp, wp)
        volume_sum = volume_sum + warped
        volume_sq_sum = volume_sq_sum + warped.square()
        count = count + inside
        warped_images.append(warped_img)
    variance = volume_sq_sum / count - (volume_sum / count).square()
    return torch.cat(warped_images + [variance], dim=1)


class VolumeNetG2(nn.Module):
    """G2: V = G2(P), a 3D U-Net (down 8->16->32->64, transposed-conv up with skip additions)."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        c0, c1, c2, c3 = cfg.unet_channels
        cin = cfg.feature_channels + 3 * cfg.views

        def down(a: int, b: int, stride: int = 1) -> ConvNormAct:
            return ConvNormAct(nn.Conv3d(a, b, 3, stride=stride, padding=1, bias=False), b, cfg)

        def up(a: int, b: int) -> nn.Sequential:
            conv = nn.ConvTranspose3d(a, b, 3, stride=2, padding=1, output_padding=1, bias=False)
            norm = BatchStatNorm(b, cfg.activation_slope, cfg.norm_eps, cfg.norm_statistics)
            return nn.Sequential(conv, norm)

        self.conv0 = down(cin, c0)
        self.conv1, self.conv2 = down(c0, c1, 2), down(c1, c1)
        self.conv3, self.conv4 = down(c1, c2, 2), down(c2, c2)
        self.conv5, self.conv6 = down(c2, c3, 2), down(c3, c3)
        self.conv7, self.conv9, self.conv11 = up(c3, c2), up(c2, c1), up(c1, c0)
        if c0 != cfg.volume_channels:
            raise ValueError("the U-Net's first stage width is the volume's channel count")

    def forward(self, cost: torch.Tensor) -> torch.Tensor:
        conv0 = self.conv0(cost)
        conv2 = self.conv2(self.conv1(conv0))
        conv4 = self.conv4(self.conv3(conv2))
        x = self.conv6(self.conv5(conv4))
        x = conv4 + self.conv7(x)
        x = conv2 + self.conv9(x)
        return conv0 + self.conv11(x)


# ---------------------------------------------------------------------------------------------
# Per-point features
# ---------------------------------------------------------------------------------------------


def project(points: torch.Tensor, intrinsics: torch.Tensor, extrinsics: torch.Tensor
            ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """World points (N,3) -> pixel u, pixel v and camera z in one view, each (N).

    Separate axes rather than one (N,3) tensor: every caller takes them apart again, and a
    per-axis division is a plain elementwise one, not a broadcast (ONNX Runtime's is far slower)."""
    cam = points @ extrinsics[:3, :3].transpose(0, 1) + extrinsics[:3, 3]
    pix = cam @ intrinsics.transpose(0, 1)
    z = pix[:, 2]
    return pix[:, 0] / z, pix[:, 1] / z, z


def reference_frustum_coordinates(
    points: torch.Tensor, intrinsics: torch.Tensor, extrinsics: torch.Tensor,
    near_far: torch.Tensor, height: int, width: int, pad: int,
) -> torch.Tensor:
    """x in the reference frustum, in [0,1]^3: u/(W-1), v/(H-1), (z-near)/(far-near), then the
    image axes remapped into the padded volume (reference code's get_ndc_coordinate)."""
    u, v, z = project(points, intrinsics, extrinsics)
    u = u / (width - 1)
    v = v / (height - 1)
    z = (z - near_far[0]) / (near_far[1] - near_far[0])
    wf, hf = width / 4.0, height / 4.0
    u = u * wf / (wf + 2 * pad) + pad / (wf + 2 * pad)
    v = v * hf / (hf + 2 * pad) + pad / (hf + 2 * pad)
    return torch.stack([u, v, z], dim=-1)


def sample_volume(volume: torch.Tensor, frustum: torch.Tensor) -> torch.Tensor:
    """s: trilinear sample of V at frustum coordinates (N,3) -> (C,N), channels first; zeros outside."""
    grid = (frustum * 2.0 - 1.0).view(1, 1, 1, -1, 3)
    s = F.grid_sample(volume, grid, mode="bilinear", padding_mode="zeros", align_corners=True)
    return s.view(volume.shape[1], -1)


def view_grid(points: torch.Tensor, intrinsics: torch.Tensor, extrinsics: torch.Tensor,
              height: int, width: int) -> torch.Tensor:
    """Pixel positions of points in one view as a grid_sample grid (align_corners=True), (N,2)."""
    u, v, _ = project(points, intrinsics, extrinsics)
    return torch.stack([u / (width - 1), v / (height - 1)], dim=-1) * 2.0 - 1.0


def same_taps_without_corner_alignment(grid: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """The grid that makes grid_sample(align_corners=False) read what grid reads with
    align_corners=True on a height x width map: x = (g + 1)(W - 1) / 2 = ((g' + 1) W - 1) / 2.
    ONNX Runtime's CPU GridSample has a fast path (taps computed once for all channels) only for
    bilinear, zero padding and align_corners=False: it halves the cost of sampling the features."""
    # Per axis with the sizes as scalars: a tensor built from them would be frozen at the tracing
    # example's size in the exported graph.
    x = ((grid[..., 0] + 1.0) * (width - 1) + 1.0) / width - 1.0
    y = ((grid[..., 1] + 1.0) * (height - 1) + 1.0) / height - 1.0
    return torch.stack([x, y], dim=-1)


def sample_views(
    points: torch.Tensor, images: torch.Tensor, features: torch.Tensor | None,
    intrinsics: torch.Tensor, extrinsics: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Reproject x into every source view.

    Returns, channels first, the colour/mask part of f, per view [r, g, b, in-image] (4V, N)
    (colours with border padding, as the reference code), and, when features are given, the
    appearance features F_a: the mean over views of [F_i, I_i] at x, zero where x falls outside a
    view (C1+3, N). Channels first is grid_sample's own layout, so nothing per point is transposed.
    All views are sampled in one grid_sample call each (the batch axis is the view).
    """
    views, _, height, width = images.shape
    grid = torch.stack([view_grid(points, intrinsics[i], extrinsics[i], height, width) for i in range(views)])
    grid4 = grid.view(views, 1, -1, 2)  # (V,1,N,2)
    inside = ((grid > -1.0) & (grid < 1.0)).all(dim=-1).to(points.dtype)[:, None]  # (V,1,N)
    # Border padding is sampling at the grid clamped to the image; clamped, the taps can take the
    # fast align_corners=False path (see same_taps_without_corner_alignment).
    colour_grid = same_taps_without_corner_alignment(grid4.clamp(-1.0, 1.0), height, width)
    rgb = F.grid_sample(images, colour_grid, mode="bilinear", padding_mode="zeros",
                        align_corners=False).view(views, 3, -1)  # (V,3,N)
    colours = torch.cat([rgb, inside], dim=1).reshape(4 * views, -1)
    if features is None:
        return colours, None
    feat_grid = same_taps_without_corner_alignment(grid4, features.shape[2], features.shape[3])
    feat = F.grid_sample(features, feat_grid, mode="bilinear", padding_mode="zeros",
                         align_corners=False).view(views, features.shape[1], -1)  # (V,C1,N)
    appearance = torch.cat([(feat * inside).sum(dim=0), (rgb * inside).sum(dim=0)]) / views
    return colours, appearance


# ---------------------------------------------------------------------------------------------
# M1..M4 and the rectifiers
# ---------------------------------------------------------------------------------------------


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
        """query (R, Q_in), keys channels first (K_in,R,S), values (R,S,C) -> rectified features (R,S,C).

        Computed in the (R, S, C) layout the trunk produces: a projection along S is a left
        product W @ X (R, S, C) -> (R, h*dk, C), so no tensor is transposed. Q is one value per
        channel token, constant along S, so per head Q K^T has inner size 2 instead of d_k:
        (q_c w + b) . k_c' = [q_c, 1] . [w . k_c', b . k_c'], with w the row sums of W_q.
        """
        rays, _, channels = values.shape
        heads, dk = self.heads, self.head_dim
        q_tokens = self.query_m3(query)  # (R,C)
        v_t = (self.w_v.weight @ values).view(rays, heads, dk, channels)  # W_v's bias: see below
        slope_offset = self._key_terms(keys).view(rays, heads, 2, channels)
        q_affine = torch.stack([q_tokens, torch.ones_like(q_tokens)], dim=-1)[:, None]  # (R,1,C,2)
        scores = q_affine @ slope_offset  # (R,h,C,C)
        attention = torch.softmax(scores, dim=-1)
        heads_t = (v_t @ attention.transpose(-1, -2)).reshape(rays, heads * dk, channels)
        # Each attention row sums to 1, so W_v's bias comes through the heads unchanged and joins
        # W_o's: one broadcast addition instead of two.
        bias = self.w_o.weight @ self.w_v.bias + self.w_o.bias
        return F.relu(values + self.w_o.weight @ heads_t + bias[:, None])

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
        self.appearance = (SampleAxisAttention(cfg, cfg.feature_channels + 3)
                           if cfg.appearance_rectification else None)

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
        points = self.radiance_points(ray_origins, ray_directions, near_far, volume, images, features,
                                      intrinsics, extrinsics)
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

        frustum = reference_frustum_coordinates(points, intrinsics[0], extrinsics[0], near_far,
                                                height, width, cfg.pad)
        s = sample_volume(volume, frustum)
        colours, appearance = sample_views(points, images, features if self.appearance is not None else None,
                                           intrinsics, extrinsics)
        point_features = torch.cat([s, colours])  # f, channels first (8+4V, N)

        unit_dir = ray_directions / torch.linalg.vector_norm(ray_directions, dim=-1, keepdim=True)
        ref_dir = unit_dir @ extrinsics[0, :3, :3].transpose(0, 1)  # d in the reference frame
        radiance = self.m1(frequency_encoding(frustum, cfg.position_freqs), point_features.transpose(0, 1))
        return RadiancePoints(z, radiance, point_features, appearance, ref_dir)

    def shade(self, points: RadiancePoints, depth_range: torch.Tensor
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

    def build_volume(self, features: torch.Tensor, images: torch.Tensor, projections: torch.Tensor,
                     depth_planes: torch.Tensor) -> torch.Tensor:
        cost = build_cost_volume(features, images, projections, depth_planes, self.cfg.pad)
        return self.volume_net(cost)
