"""COLMAP models, text or binary: cameras, images and optionally points3D, images in images/."""

from __future__ import annotations

import os
import warnings
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from .. import depth_range, lens
from ..scene import SceneData, View, check_near_far, check_scale, make_view, natural_key, resolve_background
from . import colmap_binary
from .base import DataParser

# model: number of parameters (f or fx fy, cx, cy, then the distortion in OpenCV's order), of the
# models OpenCV's lens models cover
_COLMAP_MODELS = {m: n for m, n in colmap_binary.MODELS if m not in ("FOV", "THIN_PRISM_FISHEYE")}


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


def _camera(
    record: tuple, ignore_distortion: bool, warned: set[str]
) -> tuple[np.ndarray, int, int, lens.Distortion | None]:
    """K, width, height and the lens's distortion (None when it has none, or it is ignored) of a
    camera record (id, model, width, height, parameters, where)."""
    _, model, w, h, params, where = record
    if model not in _COLMAP_MODELS:
        raise ValueError(f"{where}: camera model {model} is not supported (supported: {', '.join(_COLMAP_MODELS)})")
    if len(params) != _COLMAP_MODELS[model]:
        raise ValueError(f"{where}: {model} needs {_COLMAP_MODELS[model]} parameters, got {len(params)}")
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
            warnings.warn(f"{where}: {model} lens distortion ignored (images used as pinhole)", stacklevel=2)
        warned.add(model)
        distortion = None
    if fx <= 0 or fy <= 0 or w <= 0 or h <= 0:
        raise ValueError(f"{where}: non-positive focal length or image size")
    # COLMAP: first pixel centre at (0.5, 0.5) -> shift to integer pixel centres
    K = np.array([[fx, 0.0, cx - 0.5], [0.0, fy, cy - 0.5], [0.0, 0.0, 1.0]])
    return K, w, h, distortion


def _text_cameras(path: Path) -> list[tuple]:
    """cameras.txt -> [(camera id, model, width, height, parameters, where)]."""
    out = []
    for ln, s, t in _colmap_rows(path):
        try:
            out.append((int(t[0]), t[1].upper(), int(t[2]), int(t[3]), [float(x) for x in t[4:]], f"{path}:{ln}"))
        except (IndexError, ValueError):
            raise ValueError(f"{path}:{ln}: malformed camera line: {s!r}") from None
    return out


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


def _pose(q, t, where: str) -> np.ndarray:
    """World-to-camera of an image record's qw qx qy qz and tx ty tz."""
    try:
        rot = _quat_to_rot(*q)
    except ValueError as e:
        raise ValueError(f"{where}: {e}") from None
    w2c = np.eye(4)
    w2c[:3, :3] = rot
    w2c[:3, 3] = t
    if not np.all(np.isfinite(w2c)):
        raise ValueError(f"{where}: non-finite pose")
    return w2c


def _text_images(path: Path) -> list[tuple]:
    """images.txt -> [(image id, qw qx qy qz, tx ty tz, camera id, name, where)]. Every image takes
    two lines; the second (its 2D points) may be empty, so lines are consumed in pairs, not
    filtered."""
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
            qt = [float(x) for x in t[1:8]]
            cid = int(t[8])
            name = " ".join(t[9:])
            if not name or len(qt) != 7:
                raise ValueError
        except (IndexError, ValueError):
            raise ValueError(f"{path}:{i + 1}: malformed image line: {s!r}") from None
        out.append((iid, qt[:4], qt[4:], cid, name, f"{path}:{i + 1}"))
        i += 2  # skip the POINTS2D line
    return out


def _text_points(path: Path) -> list[tuple[list[float], list[int]]]:
    """points3D.txt -> [(x y z, ids of the images that observe it)]."""
    out = []
    for ln, _, t in _colmap_rows(path):
        try:
            out.append(([float(t[1]), float(t[2]), float(t[3])], [int(x) for x in t[8::2]]))
        except (IndexError, ValueError):
            raise ValueError(f"{path}:{ln}: malformed point line") from None
    return out


# What each encoding's files are read by: cameras, images, points.
_ENCODINGS = {
    "txt": (_text_cameras, _text_images, _text_points),
    "bin": (colmap_binary.cameras, colmap_binary.images, colmap_binary.points),
}


def find_model(root: Path) -> tuple[Path, str] | None:
    """The model's folder and encoding: <scene>, <scene>/sparse/0 or <scene>/sparse, text in any
    of them first, then binary (the Rust reader's rule, capture/src/readers/colmap/)."""
    for ext in _ENCODINGS:
        for d in (root, root / "sparse" / "0", root / "sparse"):
            if (d / f"cameras.{ext}").is_file() and (d / f"images.{ext}").is_file():
                return d, ext
    return None


def _points_near_far(points: list[tuple], images: dict[int, np.ndarray]) -> tuple[float, float] | None:
    """near = 0.9 x the 1st percentile, far = 1.1 x the 99th percentile of the z-depths of the
    points in the views that observe them (in every view if a point has no track)."""
    pair_pt, pair_img, untracked = [], [], []
    for k, (_, track) in enumerate(points):
        if track:
            pair_pt.extend([k] * len(track))
            pair_img.extend(track)
        else:
            untracked.append(k)
    if not points:
        return None
    pts = np.asarray([xyz for xyz, _ in points], dtype=np.float64)
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
        """COLMAP model, text (cameras.txt, images.txt, optional points3D.txt) or binary (.bin),
        with the images in <scene>/images/. Poses are world-to-camera in OpenCV axes (qw qx qy qz
        tx ty tz).

        The model is looked for in <scene>, <scene>/sparse/0, <scene>/sparse (``find_model``). cx,
        cy are shifted by -0.5 (COLMAP's first pixel centre is at (0.5, 0.5)); photos of a radial,
        OpenCV or fisheye camera are undistorted (:mod:`..lens`) unless ``ignore_distortion``;
        intrinsics are rescaled if the image on disk has another size than the camera (before the
        photo is undistorted). near/far: the arguments, else from the points' depths
        (``_points_near_far``), else from the poses (``depth_range``). View names are the image
        names without extension.
        """
        root = Path(path)
        if not root.is_dir():
            raise FileNotFoundError(f"COLMAP scene folder not found: {root}")
        found = find_model(root)
        if found is None:
            raise FileNotFoundError(
                f"no COLMAP model (cameras + images, .txt or .bin) in {root}, {root / 'sparse/0'} or {root / 'sparse'}"
            )
        model_dir, ext = found
        read_cameras, read_images, read_points = _ENCODINGS[ext]
        warned: set[str] = set()
        cams = {r[0]: _camera(r, ignore_distortion, warned) for r in read_cameras(model_dir / f"cameras.{ext}")}
        if not cams:
            raise ValueError(f"{model_dir / f'cameras.{ext}'}: no cameras")
        images_file = model_dir / f"images.{ext}"
        imgs = [(iid, name, _pose(q, t, where), cid) for iid, q, t, cid, name, where in read_images(images_file)]
        if not imgs:
            raise ValueError(f"{images_file}: no images")
        img_dir = root / "images"
        if not img_dir.is_dir():
            raise FileNotFoundError(f"COLMAP images folder not found: {img_dir}")
        bg = resolve_background(background, (0.0, 0.0, 0.0))
        scale = check_scale(scale)
        views: dict[str, View] = {}
        for _, name, w2c, cid in sorted(imgs, key=lambda e: natural_key(e[1])):
            if cid not in cams:
                raise ValueError(f"{images_file}: image {name} uses unknown camera {cid}")
            K, w, h, distortion = cams[cid]
            img_path = img_dir / name
            if not img_path.exists():
                warnings.warn(f"COLMAP image {img_path} is missing; skipped", stacklevel=2)
                continue
            vname = os.path.splitext(name)[0]
            views[vname] = make_view(vname, img_path, K, w2c, bg, scale, declared_size=(w, h), distortion=distortion)
        if not views:
            raise FileNotFoundError(f"none of the images listed in {images_file} exists in {img_dir}")
        pts = model_dir / f"points3D.{ext}"
        from_points = None
        if (near is None or far is None) and pts.exists():
            from_points = _points_near_far(read_points(pts), {iid: w2c for iid, _, w2c, _ in imgs})
        cameras = [v.camera for v in views.values()]
        n, f = depth_range.resolve(near, far, from_points or (None, None), cameras, str(model_dir))
        n, f = check_near_far(n, f, str(model_dir))
        return SceneData(views, n, f, bg, None, None)
