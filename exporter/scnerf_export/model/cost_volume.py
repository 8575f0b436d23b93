"""The cost volume P over D fronto-parallel planes of the reference view and G2, the 3D U-Net
that turns it into the encoding volume V (docs/design.md steps 2-3)."""

from __future__ import annotations

import itertools

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ..config import ModelConfig
from .layers import BatchStatNorm, ConvNormAct, affine_inverse, normalise_imagenet


def plane_sweep_grid(projections: torch.Tensor, depth_planes: torch.Tensor, h: int, w: int, pad: int) -> torch.Tensor:
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
        warped = F.grid_sample(
            features[i : i + 1], grid, mode="bilinear", padding_mode="zeros", align_corners=True
        ).view(1, -1, d, hp, wp)
        warped_img = F.grid_sample(
            small[i : i + 1], grid, mode="bilinear", padding_mode="zeros", align_corners=True
        ).view(1, -1, d, hp, wp)
        inside = ((grid > -1.0) & (grid < 1.0)).all(dim=-1).to(features.dtype).view(1, 1, d, hp, wp)
        volume_sum = volume_sum + warped
        volume_sq_sum = volume_sq_sum + warped.square()
        count = count + inside
        warped_images.append(warped_img)
    variance = volume_sq_sum / count - (volume_sum / count).square()
    return torch.cat(warped_images + [variance], dim=1)


# A transposed convolution of stride 2 (kernel 3, padding 1, output padding 1) along one axis:
# out[2i] = in[i]·w[1], out[2i+1] = in[i]·w[2] + in[i+1]·w[0]. Per output parity (even, odd): the
# input offset of each kernel tap it reads.
SUBPIXEL_TAPS = ({0: 1}, {0: 2, 1: 0})


def subpixel_selection(dtype: torch.dtype) -> torch.Tensor:
    """(27, 64) 0/1: which tap (kz, ky, kx) of a 3x3x3 transposed convolution's kernel each entry
    (rz, ry, rx, a, b, c) of its sub-pixel kernel holds (parities r, offsets a, b, c; see
    ``transposed_conv_as_subpixel``)."""
    selection = torch.zeros(27, 64, dtype=dtype)
    for rz, ry, rx in itertools.product((0, 1), repeat=3):
        taps = itertools.product(SUBPIXEL_TAPS[rz].items(), SUBPIXEL_TAPS[ry].items(), SUBPIXEL_TAPS[rx].items())
        for (a, kz), (b, ky), (c, kx) in taps:
            selection[(kz * 3 + ky) * 3 + kx, ((rz * 2 + ry) * 2 + rx) * 8 + (a * 2 + b) * 2 + c] = 1
    return selection


def transposed_conv_as_subpixel(x: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """``conv_transpose3d(x, weight, stride=2, padding=1, output_padding=1)`` as an ordinary
    convolution: kernel 2 over x padded by one cell at the end of each axis, 8·Co outputs (each
    output channel at each of the 8 parities of its position), interleaved into the output. The
    same products summed in another order; ONNX Runtime's ConvTranspose scatters each product into
    place (col2im) and took most of G2's time."""
    ci, co = weight.shape[:2]
    kernel = (weight.reshape(ci * co, 27) @ subpixel_selection(weight.dtype)).reshape(ci, co * 8, 2, 2, 2)
    _, _, d, h, w = x.shape
    y = F.conv3d(F.pad(x, (0, 1, 0, 1, 0, 1)), kernel.transpose(0, 1))  # (1, Co·8, d, h, w)
    y = y.reshape(co, 2, 2, 2, d, h, w).permute(0, 4, 1, 5, 2, 6, 3)  # (Co, d, rz, h, ry, w, rx)
    return y.reshape(1, co, 2 * d, 2 * h, 2 * w)


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
        return self.from_first_conv(self.conv0.conv(cost))

    def first_conv_of_slab(self, cost: torch.Tensor) -> torch.Tensor:
        """conv0's convolution (before its norm) over a slab of planes that carries one plane of
        halo on each side: (1, C, Dh, Hp, Wp) -> (1, C0, Dh - 2, Hp, Wp), each output plane the one
        that the whole volume's convolution gives (planes outside the volume arrive as zeros)."""
        return F.conv3d(cost, self.conv0.conv.weight, padding=(0, 1, 1))

    def from_first_conv(self, conv0: torch.Tensor) -> torch.Tensor:
        """The rest of G2 from conv0's convolution over the whole volume: the norm statistics are
        the whole volume's, as in ``forward``."""
        conv0 = self.conv0.bn(conv0)
        conv2 = self.conv2(self.conv1(conv0))
        conv4 = self.conv4(self.conv3(conv2))
        x = self.conv6(self.conv5(conv4))
        x = conv4 + self.upsampled(self.conv7, x)
        x = conv2 + self.upsampled(self.conv9, x)
        return conv0 + self.upsampled(self.conv11, x)

    @staticmethod
    def upsampled(block: nn.Sequential, x: torch.Tensor) -> torch.Tensor:
        """An up block (transposed convolution, norm); exported in sub-pixel form."""
        if torch.compiler.is_exporting():
            conv, norm = block
            return norm(transposed_conv_as_subpixel(x, conv.weight))
        return block(x)


def slab_halo(depth_planes: int, start: int, stop: int) -> tuple[np.ndarray, np.ndarray]:
    """Which planes feed the cost slab graph for planes ``start..stop`` of ``depth_planes``: the
    indices of those planes with one plane of halo on each side, and 1/0 for each of them inside
    or outside the volume. A halo plane outside the volume repeats the end plane's depth (a depth
    of 0 or below would divide by zero in the warp; its cost is multiplied by 0 anyway)."""
    index = np.arange(start - 1, stop + 1)
    inside = ((index >= 0) & (index < depth_planes)).astype(np.float32)
    return index.clip(0, depth_planes - 1), inside
