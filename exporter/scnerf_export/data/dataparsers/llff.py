"""LLFF scenes: poses_bounds.npy and images/ (or a downsampled images_N/)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

from ...cameras import Camera, invert_rigid, scaled_size
from ..scene import (
    SceneData,
    View,
    check_near_far,
    check_scale,
    list_images,
    read_image,
    resize_float,
    resolve_background,
)
from .base import DataParser

LLFF_HOLDOUT = 8


class LlffParser(DataParser):
    format = "llff"

    def load(
        self, path, scale: float = 1.0, background=None, near=None, far=None, ignore_distortion: bool = False
    ) -> SceneData:
        """LLFF scene: poses_bounds.npy (N x 17) + images/ (sorted file names, one per row).

        Each row is a 3x5 matrix [R | t | hwf] (camera-to-world, rotation columns in LLFF's
        [down, right, back] axes; hwf = full-resolution height, width, focal) then near, far bounds.
        OpenCV axes are [right, down, forward] = [col1, col0, -col2]. The world is kept in LLFF's
        units (no NeRF bd_factor rescale: it changes depth units, not the rendered images).
        near = min of the per-view near bounds, far = max of the far bounds.
        With scale s != 1, images_{1/s} (e.g. images_4 for s = 0.25) is used when it exists (a
        capture may ship only it), else images/ is resized. Every 8th view is a default target
        (LLFF's held-out views). Focal = f_hwf * W_used / W_hwf, principal point = (W_used/2, H_used/2).
        """
        root = Path(path)
        pb = root / "poses_bounds.npy"
        if not pb.exists():
            raise FileNotFoundError(f"LLFF poses_bounds.npy not found: {pb}")
        try:
            arr = np.load(pb, allow_pickle=False)
        except (ValueError, OSError) as e:
            raise ValueError(f"{pb}: cannot read ({e})") from None
        if arr.ndim != 2 or arr.shape[1] != 17 or arr.shape[0] == 0:
            raise ValueError(f"{pb}: expected an N x 17 array, got shape {arr.shape}")
        arr = arr.astype(np.float64)
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"{pb}: non-finite values")
        poses = arr[:, :15].reshape(-1, 3, 5)
        bounds = arr[:, 15:17]
        scale = check_scale(scale)
        files, resize_needed = self._downscaled_set(root, scale, len(poses)), False
        if files is None:
            img_root = root / "images"
            if not img_root.is_dir():
                raise FileNotFoundError(f"LLFF images folder not found: {img_root}")
            files, resize_needed = list_images(img_root), scale != 1.0
            if len(files) != len(poses):
                raise ValueError(f"{pb}: {len(poses)} poses but {len(files)} images in {img_root}")
        bg = resolve_background(background, (0.0, 0.0, 0.0))
        views: dict[str, View] = {}
        for i, f in enumerate(files):
            image = read_image(f, bg)
            if resize_needed:
                w, h = scaled_size(image.shape[1], image.shape[0], scale)
                image = np.clip(resize_float(image, w, h, Image.BILINEAR), 0.0, 1.0)
            h, w = image.shape[:2]
            H0, W0, focal = poses[i, :, 4]
            if W0 <= 0 or H0 <= 0 or focal <= 0:
                raise ValueError(f"{pb}: row {i} has invalid hwf {H0, W0, focal}")
            f_used = focal * w / W0
            K = np.array([[f_used, 0.0, w / 2.0], [0.0, f_used, h / 2.0], [0.0, 0.0, 1.0]])
            r = poses[i, :, :3]
            c2w = np.eye(4)
            c2w[:3, :3] = np.stack([r[:, 1], r[:, 0], -r[:, 2]], axis=1)
            c2w[:3, 3] = poses[i, :, 3]
            name = files[i].stem
            views[name] = View(name, image.astype(np.float32), Camera(K, invert_rigid(c2w), w, h))
        n = float(bounds[:, 0].min()) if near is None else near
        fa = float(bounds[:, 1].max()) if far is None else far
        n, fa = check_near_far(n, fa, str(pb))
        # LLFF's protocol: every 8th view is held out (its targets, never a source).
        return SceneData(views, n, fa, bg, None, list(views)[::LLFF_HOLDOUT])

    @staticmethod
    def _downscaled_set(root: Path, scale: float, count: int) -> list[Path] | None:
        """images_N for scale 1/N when it holds one image per pose (LLFF ships such sets, and
        some captures ship only them), else None (images/ is read and resized)."""
        factor = 1.0 / scale
        if scale == 1.0 or abs(factor - round(factor)) > 1e-6:
            return None
        sub = root / f"images_{int(round(factor))}"
        files = list_images(sub) if sub.is_dir() else []
        return files if len(files) == count else None
