"""Scene loaders for evaluation: DTU (MVSNet cam.txt), Blender and nerfstudio transforms.json,
LLFF poses_bounds.npy and COLMAP text models.

Every loader returns a :class:`SceneData` whose cameras are in the canonical form of the project
(DESIGN.md, "HTTP API"): OpenCV axes (x right, y down, z forward), world-to-camera, and intrinsics
in which the centre of pixel (u, v) is at image coordinates (u, v). Formats whose convention puts
the first pixel's centre at (0.5, 0.5) (COLMAP, nerfstudio) are shifted by -0.5 in cx, cy.

Image resizing (``scale``) keeps that convention (:meth:`cameras.Camera.resized`: f' = f s and
c' = (c + 0.5) s - 0.5 for the exact ratio s of the new to the old size). LLFF is the one
exception: its principal point is by definition the image centre (W/2, H/2) at whatever
resolution is used, as in LLFF's and MVSNeRF's code.
"""

from __future__ import annotations

import json
import math
import os
import re
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from .cameras import Camera, invert_rigid, opengl_c2w_to_opencv_w2c, rank_sources, scaled_size

__all__ = [
    "Camera",
    "View",
    "SceneData",
    "FORMATS",
    "load_scene",
    "load_dtu",
    "load_blender",
    "load_nerfstudio",
    "load_llff",
    "load_colmap",
    "get_views",
    "nearest_sources",
    "resize_view",
    "crop_view",
    "read_pfm",
    "DTU_SCALE",
    "DTU_DEFAULT_SOURCES",
    "DTU_DEFAULT_TARGETS",
    "LEGO_DEFAULT_SOURCES",
    "LEGO_DEFAULT_TARGETS",
]

FORMATS = ("dtu", "blender", "llff", "nerfstudio", "colmap")

# MVSNeRF's DTU world scale: millimetres * 1/200.
DTU_SCALE = 1.0 / 200.0
DTU_NUM_DEPTHS = 192  # depth_max = depth_min + depth_interval * 192 (MVSNet / MVSNeRF)
DTU_DEFAULT_SOURCES = ["25", "21", "33"]
DTU_DEFAULT_TARGETS = ["32", "24", "23", "44"]
LEGO_DEFAULT_SOURCES = ["r_6", "r_43", "r_33"]
LEGO_DEFAULT_TARGETS = ["r_63", "r_70", "r_18", "r_28"]
BLENDER_NEAR_FAR = (2.0, 6.0)

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG")


@dataclass
class View:
    name: str
    image: np.ndarray  # (H,W,3) float32 in [0,1], alpha already composited on the scene background
    camera: Camera
    depth: np.ndarray | None = None  # (H,W) float32 z-depth in the scene's (scaled) units, 0 = unknown
    mask: np.ndarray | None = None  # (H,W) bool object mask (DTU), None elsewhere


@dataclass
class SceneData:
    views: dict[str, View]
    near: float
    far: float
    background: tuple[float, float, float]
    default_sources: list[str] | None
    default_targets: list[str] | None


# ----------------------------------------------------------------------------- resizing


def _resize_float(arr: np.ndarray, width: int, height: int, resample) -> np.ndarray:
    """Resize an (H,W) or (H,W,C) float array channel by channel with PIL in float32."""
    if arr.shape[1] == width and arr.shape[0] == height:
        return arr.astype(np.float32, copy=True)
    if arr.ndim == 2:
        return np.asarray(Image.fromarray(arr.astype(np.float32), mode="F").resize((width, height), resample))
    chans = [
        np.asarray(Image.fromarray(np.ascontiguousarray(arr[..., c], dtype=np.float32), mode="F")
                   .resize((width, height), resample))
        for c in range(arr.shape[2])
    ]
    return np.stack(chans, axis=-1).astype(np.float32)


def _resize_depth(depth: np.ndarray, width: int, height: int) -> np.ndarray:
    """Nearest-neighbour resize of a depth map (0 = unknown is kept, never blended)."""
    if depth.shape[1] == width and depth.shape[0] == height:
        return depth.copy()
    # pixel-centre correct nearest neighbour: source index = floor((i + 0.5) / s)
    ys = np.clip(np.floor((np.arange(height) + 0.5) * depth.shape[0] / height).astype(int), 0, depth.shape[0] - 1)
    xs = np.clip(np.floor((np.arange(width) + 0.5) * depth.shape[1] / width).astype(int), 0, depth.shape[1] - 1)
    return depth[ys][:, xs].astype(np.float32)


def resize_view(view: View, width: int, height: int) -> View:
    """Resample a view (image bilinear/area, depth nearest, mask bilinear + threshold 0.5)."""
    image = np.clip(_resize_float(view.image, width, height, Image.BILINEAR), 0.0, 1.0)
    depth = None if view.depth is None else _resize_depth(view.depth, width, height)
    mask = None
    if view.mask is not None:
        mask = _resize_float(view.mask.astype(np.float32), width, height, Image.BILINEAR) > 0.5
    return View(view.name, image, view.camera.resized(width, height), depth, mask)


def crop_view(view: View, x0: int, y0: int, width: int, height: int) -> View:
    """Crop a view to [y0:y0+height, x0:x0+width]; the principal point moves by (-x0, -y0)."""
    h, w = view.image.shape[:2]
    if x0 < 0 or y0 < 0 or width <= 0 or height <= 0 or x0 + width > w or y0 + height > h:
        raise ValueError(f"crop ({x0},{y0},{width},{height}) is outside the {w}x{h} view {view.name!r}")
    K = view.camera.K.copy()
    K[0, 2] -= x0
    K[1, 2] -= y0
    sl = (slice(y0, y0 + height), slice(x0, x0 + width))
    return View(
        view.name,
        view.image[sl].copy(),
        Camera(K, view.camera.w2c.copy(), int(width), int(height)),
        None if view.depth is None else view.depth[sl].copy(),
        None if view.mask is None else view.mask[sl].copy(),
    )


def nearest_sources(scene: SceneData, target: str, pool: list[str], count: int = 3) -> list[str]:
    """The ``count`` views of ``pool`` nearest the target (:func:`cameras.rank_sources`: camera-centre
    distance, MVSNeRF's evaluation rule), nearest first; the target itself is never a source."""
    candidates = [name for name in pool if name != target]
    ranked = rank_sources(scene.views[target].camera, [scene.views[n].camera for n in candidates])
    if len(ranked) < count:
        raise ValueError(f"view {target!r}: only {len(ranked)} source views face its way, {count} needed")
    return [candidates[i] for i in ranked[:count]]


def get_views(scene: SceneData, names) -> list[View]:
    """Views by name (a list, or a comma-separated string); a clear KeyError for unknown names."""
    if isinstance(names, str):
        names = [n.strip() for n in names.split(",") if n.strip()]
    out = []
    for n in names:
        key = str(n)
        if key not in scene.views:
            avail = ", ".join(sorted(scene.views, key=_natural_key))
            raise KeyError(f"view {key!r} is not in the scene; available views: {avail}")
        out.append(scene.views[key])
    return out


def _natural_key(s: str):
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", s)]


# ----------------------------------------------------------------------------- image reading


def _read_image(path: Path, background: tuple[float, float, float]) -> np.ndarray:
    """(H,W,3) float32 in [0,1]; an alpha channel is composited on ``background``."""
    try:
        with Image.open(path) as im:
            im.load()
            has_alpha = im.mode in ("RGBA", "LA", "PA") or (im.mode == "P" and "transparency" in im.info)
            if im.mode in ("I;16", "I;16B", "I;16L", "I"):
                arr = np.asarray(im, dtype=np.float64) / 65535.0
                arr = np.repeat(arr[..., None], 3, axis=-1)
                return arr.astype(np.float32)
            if has_alpha:
                arr = np.asarray(im.convert("RGBA"), dtype=np.float32) / 255.0
                rgb, a = arr[..., :3], arr[..., 3:4]
                bg = np.asarray(background, dtype=np.float32).reshape(1, 1, 3)
                return (rgb * a + bg * (1.0 - a)).astype(np.float32)
            return np.asarray(im.convert("RGB"), dtype=np.float32) / 255.0
    except FileNotFoundError:
        raise FileNotFoundError(f"image not found: {path}") from None
    except (OSError, ValueError) as e:  # PIL.UnidentifiedImageError is an OSError
        raise ValueError(f"cannot read image {path}: {e}") from None


def _image_size(path: Path) -> tuple[int, int]:
    try:
        with Image.open(path) as im:
            return im.size
    except FileNotFoundError:
        raise FileNotFoundError(f"image not found: {path}") from None
    except OSError as e:
        raise ValueError(f"cannot read image {path}: {e}") from None


def _make_view(name: str, image_path: Path, K: np.ndarray, w2c: np.ndarray, background, scale: float,
               declared_size: tuple[int, int] | None = None, depth=None, mask=None) -> View:
    """Read the image, fit K to its real size (if the file declares another), apply ``scale``."""
    image = _read_image(image_path, background)
    h, w = image.shape[:2]
    cam = Camera(np.asarray(K, dtype=np.float64), np.asarray(w2c, dtype=np.float64), w, h)
    if declared_size is not None and tuple(declared_size) != (w, h):
        # intrinsics given for another resolution of the same image: rescale them
        cam = Camera(cam.K, cam.w2c, int(declared_size[0]), int(declared_size[1])).resized(w, h)
    view = View(name, image, cam, depth, mask)
    return _apply_scale(view, scale)


def _apply_scale(view: View, scale: float) -> View:
    if scale == 1.0:
        return view
    w, h = scaled_size(view.camera.width, view.camera.height, scale)
    return resize_view(view, w, h)


def _check_scale(scale: float) -> float:
    scale = float(scale)
    if not (math.isfinite(scale) and scale > 0):
        raise ValueError(f"scale must be a positive number, got {scale}")
    return scale


def _check_near_far(near: float, far: float, source: str) -> tuple[float, float]:
    near, far = float(near), float(far)
    if not (math.isfinite(near) and math.isfinite(far) and 0 <= near < far):
        raise ValueError(f"invalid near/far {near}/{far} ({source}): need 0 <= near < far")
    return near, far


def _background(background, default) -> tuple[float, float, float]:
    bg = default if background is None else background
    bg = tuple(float(x) for x in bg)
    if len(bg) != 3:
        raise ValueError(f"background must have 3 components, got {bg}")
    return bg  # type: ignore[return-value]


def _defaults_if_present(views: dict, names: list[str]) -> list[str] | None:
    return list(names) if all(n in views for n in names) else None


# ----------------------------------------------------------------------------- DTU


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
        ext = [float(t) for t in text[i_ext + len("extrinsic"):i_int].split()]
        rest = [float(t) for t in text[i_int + len("intrinsic"):].split()]
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
    m = _resize_float(m, 800, 600, Image.BILINEAR) > 0.5
    return m[44:556, 80:720].copy()


def _dtu_depth(path: Path) -> np.ndarray:
    """Depths_raw depth_map_NNNN.pfm (1600x1200, mm) -> 640x512 in scaled units (MVSNeRF:
    nearest resize by 1/2, crop x 80:720, y 44:556, times 1/200)."""
    d = read_pfm(path)
    if d.ndim != 2 or d.shape != (1200, 1600):
        raise ValueError(f"{path}: expected a 1600x1200 single-channel depth map")
    d = _resize_depth(d, 800, 600)[44:556, 80:720]
    return (d * DTU_SCALE).astype(np.float32)


def load_dtu(path, scale: float = 1.0, background=None, near=None, far=None) -> SceneData:
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
        raise FileNotFoundError(f"no MVSNet camera files (*_cam.txt) in {root / 'Cameras' / 'train'} or {root / 'Cameras'}")

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
            raise ValueError(f"cannot tell which folder of {rect_root} holds the images: {[c.name for c in candidates]}")
    img_dir = candidates[0]
    scan_name = img_dir.name[: -len("_train")] if img_dir.name.endswith("_train") else img_dir.name

    bg = _background(background, (0.0, 0.0, 0.0))
    scale = _check_scale(scale)
    views: dict[str, View] = {}
    nears, fars = [], []
    for cf in cam_files:
        mm = re.match(r"(\d+)_cam\.txt$", cf.name)
        if mm is None:
            continue
        vid = int(mm.group(1))
        img_path = img_dir / f"rect_{vid + 1:03d}_3_r5000.png"
        if not img_path.exists():
            warnings.warn(f"DTU view {vid}: camera {cf.name} has no image {img_path.name}; skipped")
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
        view = _make_view(str(vid), img_path, K, w2c, bg, 1.0, depth=depth, mask=mask)
        if view.image.shape[:2] != (512, 640):
            raise ValueError(f"{img_path}: expected a 640x512 image (MVSNeRF's DTU), got "
                             f"{view.image.shape[1]}x{view.image.shape[0]}")
        views[str(vid)] = _apply_scale(view, scale)
    if not views:
        raise FileNotFoundError(f"no DTU view of {root} has both a camera and an image")
    n, f = (near if near is not None else min(nears)), (far if far is not None else max(fars))
    n, f = _check_near_far(n, f, str(root))
    return SceneData(views, n, f, bg, _defaults_if_present(views, DTU_DEFAULT_SOURCES),
                     _defaults_if_present(views, DTU_DEFAULT_TARGETS))


# ----------------------------------------------------------------------------- transforms.json


def _read_json(path: Path) -> dict:
    try:
        with open(path) as f:
            data = json.load(f)
    except FileNotFoundError:
        raise FileNotFoundError(f"file not found: {path}") from None
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}: invalid JSON ({e})") from None
    if not isinstance(data, dict) or not isinstance(data.get("frames"), list):
        raise ValueError(f"{path}: not a transforms.json (needs a 'frames' list)")
    return data


def _resolve_image(base: Path, file_path: str) -> Path | None:
    p = (base / file_path) if not os.path.isabs(file_path) else Path(file_path)
    if p.exists():
        return p
    if not p.suffix or p.suffix not in IMAGE_EXTENSIONS:
        for ext in IMAGE_EXTENSIONS:
            q = p.with_name(p.name + ext)
            if q.exists():
                return q
    return None


def _frame_pose(frame: dict, json_path: Path, idx: int) -> np.ndarray:
    try:
        m = np.asarray(frame["transform_matrix"], dtype=np.float64)
    except (KeyError, TypeError, ValueError):
        raise ValueError(f"{json_path}: frame {idx} has no valid 'transform_matrix'") from None
    if m.shape not in ((4, 4), (3, 4)) or not np.all(np.isfinite(m)):
        raise ValueError(f"{json_path}: frame {idx} 'transform_matrix' must be a finite 4x4 matrix, got shape {m.shape}")
    return opengl_c2w_to_opencv_w2c(m)


def _unique_names(items: list[tuple[str, str]]) -> list[str]:
    """(split, stem) -> stem when the stems are unique, else 'split/stem' for every item."""
    stems = [s for _, s in items]
    if len(set(stems)) == len(stems):
        return stems
    full = [f"{sp}/{s}" if sp else s for sp, s in items]
    if len(set(full)) != len(full):
        dup = sorted({x for x in full if full.count(x) > 1})
        raise ValueError(f"duplicate view names: {dup}")
    return full


def load_blender(path, scale: float = 1.0, background=None, near=None, far=None) -> SceneData:
    """NeRF-synthetic ("Blender") scene: transforms_{train,val,test}.json (or one given json file).

    camera_angle_x -> fx = fy = 0.5 W / tan(0.5 camera_angle_x), cx = W/2, cy = H/2 (MVSNeRF's
    convention: no half-pixel shift). transform_matrix is camera-to-world in OpenGL axes. RGBA
    images are composited on ``background`` (default white). Frames whose image file does not
    exist are skipped. near/far default to 2/6. View names are the file stems ("r_6"); if two
    splits share a stem, all names become "split/stem" ("val/r_0").
    """
    p = Path(path)
    if p.is_file():
        json_files = [p]
    elif p.is_dir():
        json_files = [p / f"transforms_{s}.json" for s in ("train", "val", "test") if (p / f"transforms_{s}.json").exists()]
        if not json_files and (p / "transforms.json").exists():
            json_files = [p / "transforms.json"]
        if not json_files:
            raise FileNotFoundError(f"no transforms_{{train,val,test}}.json or transforms.json in {p}")
    else:
        raise FileNotFoundError(f"Blender scene not found: {p}")

    bg = _background(background, (1.0, 1.0, 1.0))
    scale = _check_scale(scale)
    entries = []  # (split, stem, image_path, w2c, camera_angle_x, camera_angle_y)
    for jf in json_files:
        data = _read_json(jf)
        if "camera_angle_x" not in data:
            raise ValueError(f"{jf}: no 'camera_angle_x' (for fl_x/fl_y/cx/cy files use --format nerfstudio)")
        try:
            angle_x = float(data["camera_angle_x"])
            angle_y = float(data["camera_angle_y"]) if "camera_angle_y" in data else None
        except (TypeError, ValueError):
            raise ValueError(f"{jf}: 'camera_angle_x' must be a number") from None
        if not (0 < angle_x < math.pi):
            raise ValueError(f"{jf}: camera_angle_x {angle_x} is not an angle in (0, pi)")
        m = re.match(r"transforms_(\w+)\.json$", jf.name)
        split = m.group(1) if m else ""
        for i, fr in enumerate(data["frames"]):
            if not isinstance(fr, dict) or "file_path" not in fr:
                raise ValueError(f"{jf}: frame {i} has no 'file_path'")
            img = _resolve_image(jf.parent, str(fr["file_path"]))
            if img is None:
                continue
            entries.append((split, img.stem, img, _frame_pose(fr, jf, i), angle_x, angle_y))
    if not entries:
        raise FileNotFoundError(f"none of the frames listed in {[j.name for j in json_files]} has an image file under {json_files[0].parent}")
    names = _unique_names([(e[0], e[1]) for e in entries])
    views: dict[str, View] = {}
    for name, (_, _, img, w2c, ax, ay) in zip(names, entries):
        w, h = _image_size(img)
        fx = 0.5 * w / math.tan(0.5 * ax)
        fy = fx if ay is None else 0.5 * h / math.tan(0.5 * ay)
        K = np.array([[fx, 0.0, w / 2.0], [0.0, fy, h / 2.0], [0.0, 0.0, 1.0]])
        views[name] = _make_view(name, img, K, w2c, bg, scale)
    n = BLENDER_NEAR_FAR[0] if near is None else near
    f = BLENDER_NEAR_FAR[1] if far is None else far
    n, f = _check_near_far(n, f, str(p))
    return SceneData(views, n, f, bg, _defaults_if_present(views, LEGO_DEFAULT_SOURCES),
                     _defaults_if_present(views, LEGO_DEFAULT_TARGETS))


_NS_DISTORTION = ("k1", "k2", "k3", "k4", "p1", "p2")


def load_nerfstudio(path, scale: float = 1.0, background=None, near=None, far=None) -> SceneData:
    """nerfstudio transforms.json: fl_x, fl_y, cx, cy, w, h at the top level and/or per frame,
    file_path per frame, transform_matrix camera-to-world in OpenGL axes.

    nerfstudio puts the first pixel's centre at (0.5, 0.5): cx, cy are shifted by -0.5. If the
    image on disk has another size than w x h, the intrinsics are rescaled to it. Distortion
    coefficients are ignored (with a warning). near/far come from the arguments, else from
    'near'/'far' (or 'near_far') keys in the file, else a ValueError.
    """
    p = Path(path)
    jf = p / "transforms.json" if p.is_dir() else p
    if not jf.exists():
        raise FileNotFoundError(f"nerfstudio transforms.json not found: {jf}")
    data = _read_json(jf)
    bg = _background(background, (0.0, 0.0, 0.0))
    scale = _check_scale(scale)
    model = str(data.get("camera_model", "OPENCV")).upper()
    if model not in ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE"):
        raise ValueError(f"{jf}: camera_model {model} is not supported (pinhole/OpenCV only)")

    def param(fr, key, idx):
        v = fr.get(key, data.get(key))
        if v is None:
            raise ValueError(f"{jf}: frame {idx} has no '{key}' (neither per frame nor at the top level)")
        try:
            return float(v)
        except (TypeError, ValueError):
            raise ValueError(f"{jf}: frame {idx} '{key}' is not a number: {v!r}") from None

    warned = False
    entries = []
    for i, fr in enumerate(data["frames"]):
        if not isinstance(fr, dict) or "file_path" not in fr:
            raise ValueError(f"{jf}: frame {i} has no 'file_path'")
        img = _resolve_image(jf.parent, str(fr["file_path"]))
        if img is None:
            continue
        fx = param(fr, "fl_x", i)
        fy = param(fr, "fl_y", i) if ("fl_y" in fr or "fl_y" in data) else fx
        cx, cy = param(fr, "cx", i), param(fr, "cy", i)
        w, h = int(param(fr, "w", i)), int(param(fr, "h", i))
        if fx <= 0 or fy <= 0 or w <= 0 or h <= 0:
            raise ValueError(f"{jf}: frame {i} has non-positive focal length or size")
        if not warned and any(abs(float(fr.get(k, data.get(k, 0.0)) or 0.0)) > 0 for k in _NS_DISTORTION):
            warnings.warn(f"{jf}: lens distortion coefficients are ignored (images are used as pinhole)")
            warned = True
        K = np.array([[fx, 0.0, cx - 0.5], [0.0, fy, cy - 0.5], [0.0, 0.0, 1.0]])
        rel = os.path.splitext(str(fr["file_path"]))[0]
        entries.append((rel, img, K, _frame_pose(fr, jf, i), (w, h)))
    if not entries:
        raise FileNotFoundError(f"none of the frames listed in {jf} has an image file")
    stems = [Path(e[0]).name for e in entries]
    names = stems if len(set(stems)) == len(stems) else [e[0] for e in entries]
    views = {n: _make_view(n, img, K, w2c, bg, scale, declared_size=size)
             for n, (_, img, K, w2c, size) in zip(names, entries)}
    n, f = near, far
    if n is None or f is None:
        nf = data.get("near_far")
        fn = data.get("near", nf[0] if isinstance(nf, (list, tuple)) and len(nf) == 2 else None)
        ff = data.get("far", nf[1] if isinstance(nf, (list, tuple)) and len(nf) == 2 else None)
        n = fn if n is None else n
        f = ff if f is None else f
    if n is None or f is None:
        raise ValueError(f"{jf}: no near/far in the file; pass them explicitly (--near/--far)")
    n, f = _check_near_far(n, f, str(jf))
    return SceneData(views, n, f, bg, None, None)


# ----------------------------------------------------------------------------- LLFF


def _list_images(d: Path) -> list[Path]:
    return sorted(p for p in d.iterdir() if p.is_file() and p.suffix in IMAGE_EXTENSIONS and not p.name.startswith("."))


def load_llff(path, scale: float = 1.0, background=None, near=None, far=None) -> SceneData:
    """LLFF scene: poses_bounds.npy (N x 17) + images/ (sorted file names, one per row).

    Each row is a 3x5 matrix [R | t | hwf] (camera-to-world, rotation columns in LLFF's
    [down, right, back] axes; hwf = full-resolution height, width, focal) then near, far bounds.
    OpenCV axes are [right, down, forward] = [col1, col0, -col2]. The world is kept in LLFF's
    units (no NeRF bd_factor rescale: it changes depth units, not the rendered images).
    near = min of the per-view near bounds, far = max of the far bounds.
    With scale s != 1, images_{1/s} (e.g. images_4 for s = 0.25) is used when it exists, else
    images/ is resized. Focal = f_hwf * W_used / W_hwf, principal point = (W_used/2, H_used/2).
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
    scale = _check_scale(scale)
    img_root = root / "images"
    if not img_root.is_dir():
        raise FileNotFoundError(f"LLFF images folder not found: {img_root}")
    full_files = _list_images(img_root)
    if len(full_files) != len(poses):
        raise ValueError(f"{pb}: {len(poses)} poses but {len(full_files)} images in {img_root}")
    files, resize_needed = full_files, scale != 1.0
    if scale != 1.0:
        factor = 1.0 / scale
        if abs(factor - round(factor)) < 1e-6:
            sub = root / f"images_{int(round(factor))}"
            if sub.is_dir():
                sub_files = _list_images(sub)
                if len(sub_files) == len(poses):
                    files, resize_needed = sub_files, False
    bg = _background(background, (0.0, 0.0, 0.0))
    views: dict[str, View] = {}
    for i, f in enumerate(files):
        image = _read_image(f, bg)
        if resize_needed:
            w, h = scaled_size(image.shape[1], image.shape[0], scale)
            image = np.clip(_resize_float(image, w, h, Image.BILINEAR), 0.0, 1.0)
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
        name = full_files[i].stem
        views[name] = View(name, image.astype(np.float32), Camera(K, invert_rigid(c2w), w, h))
    n = float(bounds[:, 0].min()) if near is None else near
    fa = float(bounds[:, 1].max()) if far is None else far
    n, fa = _check_near_far(n, fa, str(pb))
    return SceneData(views, n, fa, bg, None, None)


# ----------------------------------------------------------------------------- COLMAP


_COLMAP_MODELS = {
    # model: number of parameters (f or fx fy, cx, cy, then distortion, which is ignored)
    "SIMPLE_PINHOLE": 3,
    "PINHOLE": 4,
    "SIMPLE_RADIAL": 4,
    "RADIAL": 5,
    "OPENCV": 8,
    "FULL_OPENCV": 12,
}


def _colmap_lines(path: Path) -> list[str]:
    try:
        return path.read_text().splitlines()
    except FileNotFoundError:
        raise FileNotFoundError(f"COLMAP file not found: {path}") from None


def _parse_colmap_cameras(path: Path) -> dict[int, tuple[np.ndarray, int, int]]:
    cams = {}
    warned = set()
    for ln, line in enumerate(_colmap_lines(path), 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        t = s.split()
        try:
            cid, model, w, h = int(t[0]), t[1].upper(), int(t[2]), int(t[3])
            params = [float(x) for x in t[4:]]
        except (IndexError, ValueError):
            raise ValueError(f"{path}:{ln}: malformed camera line: {s!r}") from None
        if model not in _COLMAP_MODELS:
            raise ValueError(f"{path}:{ln}: camera model {model} is not supported "
                             f"(supported: {', '.join(_COLMAP_MODELS)})")
        if len(params) != _COLMAP_MODELS[model]:
            raise ValueError(f"{path}:{ln}: {model} needs {_COLMAP_MODELS[model]} parameters, got {len(params)}")
        if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
            fx = fy = params[0]
            cx, cy = params[1], params[2]
            dist = params[3:]
        else:
            fx, fy, cx, cy = params[:4]
            dist = params[4:]
        if any(abs(d) > 0 for d in dist) and model not in warned:
            warnings.warn(f"{path}: {model} distortion parameters are ignored (images are used as pinhole)")
            warned.add(model)
        if fx <= 0 or fy <= 0 or w <= 0 or h <= 0:
            raise ValueError(f"{path}:{ln}: non-positive focal length or image size")
        # COLMAP: first pixel centre at (0.5, 0.5) -> shift to integer pixel centres
        K = np.array([[fx, 0.0, cx - 0.5], [0.0, fy, cy - 0.5], [0.0, 0.0, 1.0]])
        cams[cid] = (K, w, h)
    if not cams:
        raise ValueError(f"{path}: no cameras")
    return cams


def _quat_to_rot(qw, qx, qy, qz) -> np.ndarray:
    q = np.array([qw, qx, qy, qz], dtype=np.float64)
    n = np.linalg.norm(q)
    if not np.isfinite(n) or n < 1e-12:
        raise ValueError("zero or non-finite quaternion")
    w, x, y, z = q / n
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


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
    for ln, line in enumerate(_colmap_lines(path), 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        t = s.split()
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


def load_colmap(path, scale: float = 1.0, background=None, near=None, far=None) -> SceneData:
    """COLMAP text model: cameras.txt, images.txt (qw qx qy qz tx ty tz = world-to-camera, OpenCV
    axes), optional points3D.txt, with the images in <scene>/images/.

    The model is looked for in <scene>, <scene>/sparse/0, <scene>/sparse. cx, cy are shifted by
    -0.5 (COLMAP's first pixel centre is at (0.5, 0.5)); radial/OpenCV distortion is ignored with a
    warning; intrinsics are rescaled if the image on disk has another size than cameras.txt says.
    near/far: the arguments, else from the points3D.txt depths (see _colmap_points_near_far),
    else a ValueError. View names are the image names without extension.
    """
    root = Path(path)
    if not root.is_dir():
        raise FileNotFoundError(f"COLMAP scene folder not found: {root}")
    model_dir = next((d for d in (root, root / "sparse" / "0", root / "sparse")
                      if (d / "cameras.txt").exists() and (d / "images.txt").exists()), None)
    if model_dir is None:
        raise FileNotFoundError(f"no COLMAP text model (cameras.txt + images.txt) in {root}, {root / 'sparse/0'} or {root / 'sparse'}")
    cams = _parse_colmap_cameras(model_dir / "cameras.txt")
    imgs = _parse_colmap_images(model_dir / "images.txt")
    img_dir = root / "images"
    if not img_dir.is_dir():
        raise FileNotFoundError(f"COLMAP images folder not found: {img_dir}")
    bg = _background(background, (0.0, 0.0, 0.0))
    scale = _check_scale(scale)
    views: dict[str, View] = {}
    for iid, name, w2c, cid in sorted(imgs, key=lambda e: _natural_key(e[1])):
        if cid not in cams:
            raise ValueError(f"{model_dir / 'images.txt'}: image {name} uses unknown camera {cid}")
        K, w, h = cams[cid]
        img_path = img_dir / name
        if not img_path.exists():
            warnings.warn(f"COLMAP image {img_path} is missing; skipped")
            continue
        vname = os.path.splitext(name)[0]
        views[vname] = _make_view(vname, img_path, K, w2c, bg, scale, declared_size=(w, h))
    if not views:
        raise FileNotFoundError(f"none of the images listed in {model_dir / 'images.txt'} exists in {img_dir}")
    n, f = near, far
    if n is None or f is None:
        pts = model_dir / "points3D.txt"
        nf = _colmap_points_near_far(pts, {iid: w2c for iid, _, w2c, _ in imgs}) if pts.exists() else None
        if nf is None:
            raise ValueError(f"{model_dir}: no usable points3D.txt to derive near/far from; pass them explicitly (--near/--far)")
        n = nf[0] if n is None else n
        f = nf[1] if f is None else f
    n, f = _check_near_far(n, f, str(model_dir))
    return SceneData(views, n, f, bg, None, None)


# ----------------------------------------------------------------------------- entry point

_LOADERS = {
    "dtu": load_dtu,
    "blender": load_blender,
    "llff": load_llff,
    "nerfstudio": load_nerfstudio,
    "colmap": load_colmap,
}


def load_scene(path, format: str, scale: float = 1.0, background=None, near=None, far=None) -> SceneData:
    """Load a scene folder in one of FORMATS. ``scale`` resizes every image (and its intrinsics);
    ``background`` (RGB in [0,1]) is what alpha is composited on (default white for blender, black
    otherwise); ``near``/``far`` override the format's own depth range (required for nerfstudio
    files without one and COLMAP models without points3D.txt)."""
    fmt = str(format).lower()
    if fmt not in _LOADERS:
        raise ValueError(f"unknown scene format {format!r}; expected one of {', '.join(FORMATS)}")
    return _LOADERS[fmt](path, scale=scale, background=background, near=near, far=far)
