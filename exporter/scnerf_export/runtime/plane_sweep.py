"""The cost volume of a slab of depth planes, computed outside ONNX as the server computes it
(server/src/pipeline/sweep.rs, the same formulas in the same order): the sources' images and
features warped onto each fronto-parallel plane of the reference view by its homography, and the
features' variance over the views. It is ``model.cost_volume.build_cost_volume`` (the definition,
in PyTorch), written for one plane at a time.

Per plane and source view the homography gives every cell of the padded reference grid a point of
the source's feature grid; the bilinear taps of that point (zero outside the grid) are computed
once and read for every channel. That is what makes it fast: ONNX Runtime's GridSample recomputes
them per channel.
"""

from __future__ import annotations

import numpy as np

# The cost volume reads the images ImageNet-normalised (model.layers.normalise_imagenet).
IMAGENET_MEAN = np.array([0.485, 0.456, 0.406], np.float32)
IMAGENET_STD = np.array([0.229, 0.224, 0.225], np.float32)


def quarter_images(images: np.ndarray) -> np.ndarray:
    """(V,3,H,W) -> (V,3,H/4,W/4): ImageNet-normalised, then bilinear at a quarter of the size
    (``F.interpolate(align_corners=False)``: each cell the mean of pixels 1 and 2 of its 4x4 block
    in both directions; PyTorch's kernel sums them in an order that depends on the size, this is
    its order for large images, one ulp from the other)."""
    x = (images - IMAGENET_MEAN.reshape(1, 3, 1, 1)) / IMAGENET_STD.reshape(1, 3, 1, 1)
    top = x[:, :, 1::4, 1::4] + x[:, :, 1::4, 2::4]
    bottom = x[:, :, 2::4, 1::4] + x[:, :, 2::4, 2::4]
    return ((top + bottom) * np.float32(0.25)).astype(np.float32)


def affine_inverse(m: np.ndarray) -> np.ndarray:
    """The inverse of [[A, b], [0, 1]] by A's adjugate, as ``model.layers.affine_inverse``."""
    a = m[:3, :3]
    r0, r1, r2 = a
    cofactor_t = np.stack([np.cross(r1, r2), np.cross(r2, r0), np.cross(r0, r1)], axis=-1)
    det = (r0 * np.cross(r1, r2)).sum()
    inverse = np.eye(4, dtype=np.float32)
    inverse[:3, :3] = cofactor_t / det
    inverse[:3, 3] = -(inverse[:3, :3] @ m[:3, 3])
    return inverse


def source_homographies(projections: np.ndarray) -> np.ndarray:
    """(V-1,3,4): for each source view, [R | t] with source pixel·depth = R [x, y, 1] + t / z for
    the reference cell (x, y) on the plane at depth z."""
    return (projections[1:] @ affine_inverse(projections[0]))[:, :3, :]


def bilinear_taps(gx: np.ndarray, gy: np.ndarray, h: int, w: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """grid_sample's bilinear taps (align_corners=True, zero padding) at grid points (gx, gy) in
    [-1, 1] of an h x w map: (flat index, weight) of the nw, ne, sw, se neighbours; a tap outside
    the map reads index 0 with weight 0 (grid_sample reads a 0 there: the same sum)."""
    x = (gx + np.float32(1)) * np.float32((w - 1) / 2)
    y = (gy + np.float32(1)) * np.float32((h - 1) / 2)
    x_w, y_n = np.floor(x), np.floor(y)
    e_, n_ = x - x_w, y - y_n
    w_, s_ = np.float32(1) - e_, np.float32(1) - n_
    taps = []
    for dy, dx, weight in ((0, 0, s_ * w_), (0, 1, s_ * e_), (1, 0, n_ * w_), (1, 1, n_ * e_)):
        col, row = x_w + dx, y_n + dy
        valid = (col >= 0) & (col <= w - 1) & (row >= 0) & (row <= h - 1)
        index = np.where(valid, row, 0).astype(np.int64) * w + np.where(valid, col, 0).astype(np.int64)
        taps.append((index, np.where(valid, weight, np.float32(0))))
    return taps


def warp(source: np.ndarray, taps) -> np.ndarray:
    """(C, h·w) channels sampled at the taps: (C, cells)."""
    total = None
    for index, weight in taps:
        value = source[:, index] * weight
        total = value if total is None else total + value
    return total


def sweep_plane(
    sources: list[np.ndarray],
    reference: np.ndarray,
    homographies: np.ndarray,
    depth: np.float32,
    pad: int,
    h: int,
    w: int,
) -> np.ndarray:
    """One plane of the cost volume, (3V + C, Hp, Wp). ``sources``: per source view its (3 + C,
    h·w) quarter image and features; ``reference``: the reference view's, padded, (3 + C, Hp·Wp)."""
    hp, wp = h + 2 * pad, w + 2 * pad
    ys, xs = np.meshgrid(np.arange(hp, dtype=np.float32) - pad, np.arange(wp, dtype=np.float32) - pad, indexing="ij")
    xs, ys = xs.reshape(-1), ys.reshape(-1)
    ref_features = reference[3:]
    total, squares = ref_features.copy(), ref_features * ref_features
    count = np.ones_like(xs)
    images = [reference[:3]]
    for source, m in zip(sources, homographies):
        px, py, pz = ((m[k, 0] * xs + m[k, 1] * ys) + m[k, 2] + m[k, 3] / depth for k in range(3))
        gx = px / pz / np.float32((w - 1) / 2) - np.float32(1)
        gy = py / pz / np.float32((h - 1) / 2) - np.float32(1)
        warped = warp(source, bilinear_taps(gx, gy, h, w))
        images.append(warped[:3])
        total = total + warped[3:]
        squares = squares + warped[3:] * warped[3:]
        count = count + ((gx > -1) & (gx < 1) & (gy > -1) & (gy < 1)).astype(np.float32)
    variance = squares / count - (total / count) * (total / count)
    return np.concatenate(images + [variance]).reshape(-1, hp, wp)


def sweep(
    features: np.ndarray,
    images: np.ndarray,
    projections: np.ndarray,
    depth_planes: np.ndarray,
    plane_inside: np.ndarray,
    pad: int,
) -> np.ndarray:
    """The cost volume (1, 3V + C, D, Hp, Wp) on ``depth_planes``, zero on the planes where
    ``plane_inside`` is 0 (a slab's halo planes outside the volume)."""
    views, channels, h, w = features.shape
    small = quarter_images(images)
    stacked = np.concatenate([small, features], axis=1)  # (V, 3 + C, h, w)
    reference = np.pad(stacked[0], ((0, 0), (pad, pad), (pad, pad))).reshape(3 + channels, -1)
    sources = [stacked[i].reshape(3 + channels, -1) for i in range(1, views)]
    homographies = source_homographies(projections)
    hp, wp = h + 2 * pad, w + 2 * pad
    cost = np.zeros((1, 3 * views + channels, len(depth_planes), hp, wp), np.float32)
    for k, (depth, inside) in enumerate(zip(depth_planes, plane_inside)):
        if inside:
            cost[0, :, k] = sweep_plane(sources, reference, homographies, np.float32(depth), pad, h, w)
    return cost
