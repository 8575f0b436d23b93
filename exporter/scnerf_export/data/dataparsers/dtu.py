"""DTU in MVSNeRF's layout: MVSNet cam.txt cameras, rectified images, optional masks and depths."""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import numpy as np
from PIL import Image

from ..scene import (
    SceneData,
    View,
    apply_scale,
    check_near_far,
    check_scale,
    defaults_if_present,
    make_view,
    resize_depth,
    resize_float,
    resolve_background,
)
from .base import DataParser

# MVSNeRF's DTU world scale: millimetres * 1/200.
DTU_SCALE = 1.0 / 200.0
DTU_NUM_DEPTHS = 192  # depth_max = depth_min + depth_interval * 192 (MVSNet / MVSNeRF)
DTU_DEFAULT_SOURCES = ["25", "21", "33"]
DTU_DEFAULT_TARGETS = ["32", "24", "23", "44"]


def _parse_dtu_cam(path: Path) -> tuple[np.ndarray, np.ndarray, float, float]:
    """MVSNet cam.txt -> (w2c 4x4 in mm, K 3x3 as written, depth_min, depth_interval)."""
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise FileNotFoundError(f"camera file not found: {path}") from None
    low = text.lower()
    i_ext, i_int = low.find("extrinsic"), low.find("intrinsic")
    if i_ext < 0 or i_int < 0 or i_int < i_ext:
        raise ValueError(f"{path}: not an MVSNet cam.txt (needs 'extrinsic' then 'intrinsic' sections)")
    try:
        ext = [float(t) for t in text[i_ext + len("extrinsic") : i_int].split()]
        rest = [float(t) for t in text[i_int + len("intrinsic") :].split()]
    except ValueError as e:
        raise ValueError(f"{path}: malformed number in cam.txt ({e})") from None
    if len(ext) != 16:
        raise ValueError(f"{path}: extrinsic must have 16 numbers, found {len(ext)}")
    if len(rest) < 11:
        raise ValueError(f"{path}: need 9 intrinsic numbers then 'depth_min depth_interval', found {len(rest)} numbers")
    w2c = np.array(ext, dtype=np.float64).reshape(4, 4)
    K = np.array(rest[:9], dtype=np.float64).reshape(3, 3)
    depth_min, depth_interval = rest[9], rest[10]
    if not np.all(np.isfinite(w2c)) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError(f"{path}: non-finite or invalid camera matrices")
    if not (depth_min > 0 and depth_interval > 0):
        raise ValueError(f"{path}: invalid depth range {depth_min} {depth_interval}")
    return w2c, K, depth_min, depth_interval


def read_pfm(path: Path) -> np.ndarray:
    """Read a PFM file (as written by MVSNet) -> (H,W) or (H,W,3) float32, top row first."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            header = f.readline().decode("latin-1").strip()
            if header not in ("PF", "Pf"):
                raise ValueError(f"{path}: not a PFM file")
            dims = f.readline().decode("latin-1").split()
            while not dims:  # tolerate blank lines
                dims = f.readline().decode("latin-1").split()
            w, h = int(dims[0]), int(dims[1])
            scale = float(f.readline().decode("latin-1").strip())
            endian = "<" if scale < 0 else ">"
            chans = 3 if header == "PF" else 1
            data = np.frombuffer(f.read(), dtype=endian + "f4")
    except FileNotFoundError:
        raise FileNotFoundError(f"PFM file not found: {path}") from None
    except (IndexError, UnicodeDecodeError) as e:
        raise ValueError(f"{path}: malformed PFM header ({e})") from None
    if data.size < w * h * chans:
        raise ValueError(f"{path}: truncated PFM data")
    shape = (h, w, 3) if chans == 3 else (h, w)
    return np.flipud(data[: w * h * chans].reshape(shape)).astype(np.float32)


def _dtu_mask(path: Path) -> np.ndarray:
    """mask_1600x1200/NNN.png -> 640x512 bool: bilinear resize to 800x600 (PIL, float), threshold
    0.5, crop x 80:720, y 44:556: the same transform as the 640x512 images."""
    try:
        with Image.open(path) as im:
            m = np.asarray(im.convert("L"), dtype=np.float32) / 255.0
    except OSError as e:
        raise ValueError(f"cannot read DTU mask {path}: {e}") from None
    if m.shape != (1200, 1600):
        raise ValueError(f"{path}: expected a 1600x1200 mask, got {m.shape[1]}x{m.shape[0]}")
    m = resize_float(m, 800, 600, Image.BILINEAR) > 0.5
    return m[44:556, 80:720].copy()


def _dtu_depth(path: Path) -> np.ndarray:
    """Depths_raw depth_map_NNNN.pfm (1600x1200, mm) -> 640x512 in scaled units (MVSNeRF:
    nearest resize by 1/2, crop x 80:720, y 44:556, times 1/200)."""
    d = read_pfm(path)
    if d.ndim != 2 or d.shape != (1200, 1600):
        raise ValueError(f"{path}: expected a 1600x1200 single-channel depth map")
    d = resize_depth(d, 800, 600)[44:556, 80:720]
    return (d * DTU_SCALE).astype(np.float32)


class DtuParser(DataParser):
    format = "dtu"

    def load(
        self, path, scale: float = 1.0, background=None, near=None, far=None, ignore_distortion: bool = False
    ) -> SceneData:
        """A DTU scan in MVSNeRF's layout (see module docstring of the project data README).

        Cameras/train/000000NN_cam.txt (or Cameras/000000NN_cam.txt): MVSNet layout, world-to-camera
        in mm, intrinsics at 1/4 of 640x512 (multiplied by 4 here, MVSNeRF's convention: no half-pixel
        shift). The world is scaled by 1/200. near = min over views of depth_min/200, far = max over
        views of (depth_min + 192 * depth_interval)/200 (2.125 / 4.525 for the usual "425 2.5").
        View NN's image: Rectified/scanS_train/rect_{NN+1:03d}_3_r5000.png (lighting 3, 640x512).
        Optional: mask_1600x1200/{NN:03d}.png (object mask) and Depths_raw/scanS/depth_map_{NN:04d}.pfm
        (ground-truth depth).
        """
        root = Path(path)
        if not root.is_dir():
            raise FileNotFoundError(f"DTU scene folder not found: {root}")
        cam_dir = root / "Cameras" / "train"
        if not cam_dir.is_dir():
            cam_dir = root / "Cameras"
        cam_files = sorted(cam_dir.glob("*_cam.txt")) if cam_dir.is_dir() else []
        if not cam_files:
            raise FileNotFoundError(
                f"no MVSNet camera files (*_cam.txt) in {root / 'Cameras' / 'train'} or {root / 'Cameras'}"
            )

        m = re.search(r"scan(\d+)", root.name)
        rect_root = root / "Rectified"
        if not rect_root.is_dir():
            raise FileNotFoundError(f"DTU images folder not found: {rect_root}")
        candidates = sorted(p for p in rect_root.iterdir() if p.is_dir())
        if m is not None:
            preferred = [p for p in candidates if p.name in (f"scan{m.group(1)}_train", f"scan{m.group(1)}")]
            candidates = preferred or candidates
        if len(candidates) != 1:
            if not candidates and any(rect_root.glob("rect_*.png")):
                candidates = [rect_root]
            else:
                raise ValueError(
                    f"cannot tell which folder of {rect_root} holds the images: {[c.name for c in candidates]}"
                )
        img_dir = candidates[0]
        scan_name = img_dir.name[: -len("_train")] if img_dir.name.endswith("_train") else img_dir.name

        bg = resolve_background(background, (0.0, 0.0, 0.0))
        scale = check_scale(scale)
        views: dict[str, View] = {}
        nears, fars = [], []
        for cf in cam_files:
            mm = re.match(r"(\d+)_cam\.txt$", cf.name)
            if mm is None:
                continue
            vid = int(mm.group(1))
            img_path = img_dir / f"rect_{vid + 1:03d}_3_r5000.png"
            if not img_path.exists():
                warnings.warn(f"DTU view {vid}: camera {cf.name} has no image {img_path.name}; skipped", stacklevel=2)
                continue
            w2c, K, dmin, dint = _parse_dtu_cam(cf)
            w2c = w2c.copy()
            w2c[:3, 3] *= DTU_SCALE
            K = K.copy()
            K[:2] *= 4.0
            nears.append(dmin * DTU_SCALE)
            fars.append((dmin + dint * DTU_NUM_DEPTHS) * DTU_SCALE)
            mask_path = root / "mask_1600x1200" / f"{vid:03d}.png"
            mask = _dtu_mask(mask_path) if mask_path.exists() else None
            depth_path = root / "Depths_raw" / scan_name / f"depth_map_{vid:04d}.pfm"
            depth = _dtu_depth(depth_path) if depth_path.exists() else None
            view = make_view(str(vid), img_path, K, w2c, bg, 1.0, depth=depth, mask=mask)
            if view.image.shape[:2] != (512, 640):
                raise ValueError(
                    f"{img_path}: expected a 640x512 image (MVSNeRF's DTU), got "
                    f"{view.image.shape[1]}x{view.image.shape[0]}"
                )
            views[str(vid)] = apply_scale(view, scale)
        if not views:
            raise FileNotFoundError(f"no DTU view of {root} has both a camera and an image")
        n, f = (near if near is not None else min(nears)), (far if far is not None else max(fars))
        n, f = check_near_far(n, f, str(root))
        return SceneData(
            views,
            n,
            f,
            bg,
            defaults_if_present(views, DTU_DEFAULT_SOURCES),
            defaults_if_present(views, DTU_DEFAULT_TARGETS),
        )
