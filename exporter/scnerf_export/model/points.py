"""Per sample point x: its reference-frustum coordinates, the volume sample s and the source
views' colours, masks and features at its reprojections (docs/design.md step 4)."""

from __future__ import annotations

import torch
import torch.nn.functional as F


def project(
    points: torch.Tensor, intrinsics: torch.Tensor, extrinsics: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """World points (N,3) -> pixel u, pixel v and camera z in one view, each (N).

    Separate axes rather than one (N,3) tensor: every caller takes them apart again, and a
    per-axis division is a plain elementwise one, not a broadcast (ONNX Runtime's is far slower)."""
    cam = points @ extrinsics[:3, :3].transpose(0, 1) + extrinsics[:3, 3]
    pix = cam @ intrinsics.transpose(0, 1)
    z = pix[:, 2]
    return pix[:, 0] / z, pix[:, 1] / z, z


def reference_frustum_coordinates(
    points: torch.Tensor,
    intrinsics: torch.Tensor,
    extrinsics: torch.Tensor,
    near_far: torch.Tensor,
    height: int,
    width: int,
    pad: int,
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


def view_grid(
    points: torch.Tensor, intrinsics: torch.Tensor, extrinsics: torch.Tensor, height: int, width: int
) -> torch.Tensor:
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
    points: torch.Tensor,
    images: torch.Tensor,
    features: torch.Tensor | None,
    intrinsics: torch.Tensor,
    extrinsics: torch.Tensor,
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
    rgb = F.grid_sample(images, colour_grid, mode="bilinear", padding_mode="zeros", align_corners=False).view(
        views, 3, -1
    )  # (V,3,N)
    colours = torch.cat([rgb, inside], dim=1).reshape(4 * views, -1)
    if features is None:
        return colours, None
    feat_grid = same_taps_without_corner_alignment(grid4, features.shape[2], features.shape[3])
    feat = F.grid_sample(features, feat_grid, mode="bilinear", padding_mode="zeros", align_corners=False).view(
        views, features.shape[1], -1
    )  # (V,C1,N)
    appearance = torch.cat([(feat * inside).sum(dim=0), (rgb * inside).sum(dim=0)]) / views
    return colours, appearance
