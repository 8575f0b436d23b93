"""COLMAP text models: cameras.txt, images.txt and optionally points3D.txt, images in images/."""

from __future__ import annotations

import os
import warnings
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from .. import depth_range, lens
from ..scene import SceneData, View, check_near_far, check_scale, make_view, natural_key, resolve_background
from .base import DataParser

_COLMAP_MODELS = {
    # model: number of parameters (f or fx fy, cx, cy, then distortion in OpenCV's order)
    "SIMPLE_PINHOLE": 3,
    "PINHOLE": 4,
    "SIMPLE_RADIAL": 4,
    "RADIAL": 5,
    "OPENCV": 8,
    "FULL_OPENCV": 12,
    "OPENCV_FISHEYE": 8,
    "SIMPLE_RADIAL_FISHEYE": 4,
    "RADIAL_FISHEYE": 5,
}


def _colmap_lines(path: Path) -> list[str]:
    try:
        return path.read_text().splitlines()
    except FileNotFoundError:
        raise FileNotFoundError(f"COLMAP file not found: {path}") from None


def _colmap_rows(path: Path) -> Iterator[tuple[int, str, list[str]]]:
    """(line number, line, its fields) of every line that is neither blank nor a comment."""
    for ln, line in enumerate(_colmap_lines(path), 1):
        s = line.strip()
        if s and not s.startswith("#"):
            yield ln, s, s.split()


def _parse_colmap_cameras(
    path: Path, ignore_distortion: bool
) -> dict[int, tuple[np.ndarray, int, int, lens.Distortion | None]]:
    """Per camera id: K, width, height and the lens's distortion (None when it has none, or it is
    ignored)."""
    cams = {}
    warned = set()
    for ln, s, t in _colmap_rows(path):
        try:
            cid, model, w, h = int(t[0]), t[1].upper(), int(t[2]), int(t[3])
            params = [float(x) for x in t[4:]]
        except (IndexError, ValueError):
            raise ValueError(f"{path}:{ln}: malformed camera line: {s!r}") from None
        if model not in _COLMAP_MODELS:
            raise ValueError(
                f"{path}:{ln}: camera model {model} is not supported (supported: {', '.join(_COLMAP_MODELS)})"
            )
        if len(params) != _COLMAP_MODELS[model]:
            raise ValueError(f"{path}:{ln}: {model} needs {_COLMAP_MODELS[model]} parameters, got {len(params)}")
        if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL", "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE"):
            fx = fy = params[0]
            cx, cy = params[1], params[2]
            dist = params[3:]
        else:
            fx, fy, cx, cy = params[:4]
            dist = params[4:]
        distortion = (lens.fisheye if "FISHEYE" in model else lens.perspective)(*dist)
        if distortion is not None and ignore_distortion:
            if model not in warned:
                warnings.warn(f"{path}: {model} lens distortion ignored (images used as pinhole)", stacklevel=2)
            warned.add(model)
            distortion = None
        if fx <= 0 or fy <= 0 or w <= 0 or h <= 0:
            raise ValueError(f"{path}:{ln}: non-positive focal length or image size")
        # COLMAP: first pixel centre at (0.5, 0.5) -> shift to integer pixel centres
        K = np.array([[fx, 0.0, cx - 0.5], [0.0, fy, cy - 0.5], [0.0, 0.0, 1.0]])
        cams[cid] = (K, w, h, distortion)
    if not cams:
        raise ValueError(f"{path}: no cameras")
    return cams


def _quat_to_rot(qw, qx, qy, qz) -> np.ndarray:
    q = np.array([qw, qx, qy, qz], dtype=np.float64)
    n = np.linalg.norm(q)
    if not np.isfinite(n) or n < 1e-12:
        raise ValueError("zero or non-finite quaternion")
    w, x, y, z = q / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _parse_colmap_images(path: Path) -> list[tuple[int, str, np.ndarray, int]]:
    """images.txt -> [(image_id, name, w2c, camera_id)]. Every image takes two lines; the second
    (its 2D points) may be empty, so lines are consumed in pairs, not filtered."""
    out = []
    lines = _colmap_lines(path)
    i = 0
    while i < len(lines):
        s = lines[i].strip()
        if not s or s.startswith("#"):
            i += 1
            continue
        t = s.split()
        try:
            iid = int(t[0])
            qw, qx, qy, qz, tx, ty, tz = (float(x) for x in t[1:8])
            cid = int(t[8])
            name = " ".join(t[9:])
            if not name:
                raise ValueError
        except (IndexError, ValueError):
            raise ValueError(f"{path}:{i + 1}: malformed image line: {s!r}") from None
        try:
            rot = _quat_to_rot(qw, qx, qy, qz)
        except ValueError as e:
            raise ValueError(f"{path}:{i + 1}: {e}") from None
        w2c = np.eye(4)
        w2c[:3, :3] = rot
        w2c[:3, 3] = [tx, ty, tz]
        if not np.all(np.isfinite(w2c)):
            raise ValueError(f"{path}:{i + 1}: non-finite pose")
        out.append((iid, name, w2c, cid))
        i += 2  # skip the POINTS2D line
    if not out:
        raise ValueError(f"{path}: no images")
    return out


def _colmap_points_near_far(path: Path, images: dict[int, np.ndarray]) -> tuple[float, float] | None:
    """near = 0.9 x the 1st percentile, far = 1.1 x the 99th percentile of the z-depths of the
    points in the views that observe them (in every view if a point has no track)."""
    xyz, pair_pt, pair_img, untracked = [], [], [], []
    for ln, _, t in _colmap_rows(path):
        try:
            xyz.append([float(t[1]), float(t[2]), float(t[3])])
            track = [int(x) for x in t[8::2]]
        except (IndexError, ValueError):
            raise ValueError(f"{path}:{ln}: malformed point line") from None
        k = len(xyz) - 1
        if track:
            pair_pt.extend([k] * len(track))
            pair_img.extend(track)
        else:
            untracked.append(k)
    if not xyz:
        return None
    pts = np.asarray(xyz, dtype=np.float64)
    pair_pt_a, pair_img_a = np.asarray(pair_pt, dtype=np.int64), np.asarray(pair_img, dtype=np.int64)
    untracked_a = np.asarray(untracked, dtype=np.int64)
    depths = []
    for iid, w2c in images.items():
        idx = np.concatenate([pair_pt_a[pair_img_a == iid], untracked_a])
        if idx.size == 0:
            continue
        z = pts[idx] @ w2c[2, :3] + w2c[2, 3]
        depths.append(z[z > 1e-9])
    d = np.concatenate(depths) if depths else np.zeros(0)
    if d.size == 0:
        return None
    return 0.9 * float(np.percentile(d, 1)), 1.1 * float(np.percentile(d, 99))


class ColmapParser(DataParser):
    format = "colmap"

    def load(
        self, path, scale: float = 1.0, background=None, near=None, far=None, ignore_distortion: bool = False
    ) -> SceneData:
        """COLMAP text model: cameras.txt, images.txt (qw qx qy qz tx ty tz = world-to-camera, OpenCV
        axes), optional points3D.txt, with the images in <scene>/images/.

        The model is looked for in <scene>, <scene>/sparse/0, <scene>/sparse. cx, cy are shifted by
        -0.5 (COLMAP's first pixel centre is at (0.5, 0.5)); photos of a radial, OpenCV or fisheye
        camera are undistorted (:mod:`..lens`) unless ``ignore_distortion``; intrinsics are rescaled if the image
        on disk has another size than cameras.txt says (before the photo is undistorted). near/far:
        the arguments, else from the points3D.txt depths (see _colmap_points_near_far), else from
        the poses (``depth_range``). View names are the image names without extension.
        """
        root = Path(path)
        if not root.is_dir():
            raise FileNotFoundError(f"COLMAP scene folder not found: {root}")
        model_dir = next(
            (
                d
                for d in (root, root / "sparse" / "0", root / "sparse")
                if (d / "cameras.txt").exists() and (d / "images.txt").exists()
            ),
            None,
        )
        if model_dir is None:
            raise FileNotFoundError(
                f"no COLMAP text model (cameras.txt + images.txt) in {root}, {root / 'sparse/0'} or {root / 'sparse'}"
            )
        cams = _parse_colmap_cameras(model_dir / "cameras.txt", ignore_distortion)
        imgs = _parse_colmap_images(model_dir / "images.txt")
        img_dir = root / "images"
        if not img_dir.is_dir():
            raise FileNotFoundError(f"COLMAP images folder not found: {img_dir}")
        bg = resolve_background(background, (0.0, 0.0, 0.0))
        scale = check_scale(scale)
        views: dict[str, View] = {}
        for _, name, w2c, cid in sorted(imgs, key=lambda e: natural_key(e[1])):
            if cid not in cams:
                raise ValueError(f"{model_dir / 'images.txt'}: image {name} uses unknown camera {cid}")
            K, w, h, distortion = cams[cid]
            img_path = img_dir / name
            if not img_path.exists():
                warnings.warn(f"COLMAP image {img_path} is missing; skipped", stacklevel=2)
                continue
            vname = os.path.splitext(name)[0]
            views[vname] = make_view(vname, img_path, K, w2c, bg, scale, declared_size=(w, h), distortion=distortion)
        if not views:
            raise FileNotFoundError(f"none of the images listed in {model_dir / 'images.txt'} exists in {img_dir}")
        pts = model_dir / "points3D.txt"
        from_points = None
        if (near is None or far is None) and pts.exists():
            from_points = _colmap_points_near_far(pts, {iid: w2c for iid, _, w2c, _ in imgs})
        cameras = [v.camera for v in views.values()]
        n, f = depth_range.resolve(near, far, from_points or (None, None), cameras, str(model_dir))
        n, f = check_near_far(n, f, str(model_dir))
        return SceneData(views, n, f, bg, None, None)
