"""A scene loaded from disk: its views (image, canonical camera, optional depth and object mask)
and the [near, far] that brackets them, with what every format's parser shares: image reading,
resizing, cropping and argument checks.

Cameras are in the project's canonical form (docs/design.md, "HTTP API"; :mod:`scnerf_export.cameras`):
OpenCV axes, world-to-camera, the centre of pixel (u, v) at image coordinates (u, v).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from ..cameras import Camera, scaled_size
from . import lens

# Extensions of the images the parsers use, in any case (IMG_0001.JPG, a.Png): the Rust readers'
# rule too (capture/src/readers/names.rs), held together by tests/fixtures/rules/image_files.json.
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg")


def is_image(path: Path) -> bool:
    """Whether ``path`` names an image the parsers use, by its extension in any case."""
    return path.suffix.lower() in IMAGE_EXTENSIONS


def list_images(folder: Path) -> list[Path]:
    """The images of ``folder`` in name order, hidden files (``._IMG.JPG``, ``.x.png``) left out."""
    return sorted(p for p in folder.iterdir() if p.is_file() and is_image(p) and not p.name.startswith("."))


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


def resize_float(arr: np.ndarray, width: int, height: int, resample) -> np.ndarray:
    """Resize an (H,W) or (H,W,C) float array channel by channel with PIL in float32."""
    if arr.shape[1] == width and arr.shape[0] == height:
        return arr.astype(np.float32, copy=True)
    if arr.ndim == 2:
        return np.asarray(Image.fromarray(arr.astype(np.float32), mode="F").resize((width, height), resample))
    chans = [
        np.asarray(
            Image.fromarray(np.ascontiguousarray(arr[..., c], dtype=np.float32), mode="F").resize(
                (width, height), resample
            )
        )
        for c in range(arr.shape[2])
    ]
    return np.stack(chans, axis=-1).astype(np.float32)


def resize_depth(depth: np.ndarray, width: int, height: int) -> np.ndarray:
    """Nearest-neighbour resize of a depth map (0 = unknown is kept, never blended)."""
    if depth.shape[1] == width and depth.shape[0] == height:
        return depth.copy()
    # pixel-centre correct nearest neighbour: source index = floor((i + 0.5) / s)
    ys = np.clip(np.floor((np.arange(height) + 0.5) * depth.shape[0] / height).astype(int), 0, depth.shape[0] - 1)
    xs = np.clip(np.floor((np.arange(width) + 0.5) * depth.shape[1] / width).astype(int), 0, depth.shape[1] - 1)
    return depth[ys][:, xs].astype(np.float32)


def resize_view(view: View, width: int, height: int) -> View:
    """Resample a view (image bilinear/area, depth nearest, mask bilinear + threshold 0.5)."""
    image = np.clip(resize_float(view.image, width, height, Image.BILINEAR), 0.0, 1.0)
    depth = None if view.depth is None else resize_depth(view.depth, width, height)
    mask = None
    if view.mask is not None:
        mask = resize_float(view.mask.astype(np.float32), width, height, Image.BILINEAR) > 0.5
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


def natural_key(s: str):
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", s)]


def read_image(path: Path, background: tuple[float, float, float]) -> np.ndarray:
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


def image_size(path: Path) -> tuple[int, int]:
    try:
        with Image.open(path) as im:
            return im.size
    except FileNotFoundError:
        raise FileNotFoundError(f"image not found: {path}") from None
    except OSError as e:
        raise ValueError(f"cannot read image {path}: {e}") from None


def make_view(
    name: str,
    image_path: Path,
    K: np.ndarray,
    w2c: np.ndarray,
    background,
    scale: float,
    declared_size: tuple[int, int] | None = None,
    depth=None,
    mask=None,
    distortion: lens.Distortion | None = None,
) -> View:
    """Read the image, fit K to its real size (if the file declares another), resample it to a
    pinhole camera if its lens has a ``distortion`` (:mod:`.lens`), apply ``scale``."""
    image = read_image(image_path, background)
    h, w = image.shape[:2]
    cam = Camera(np.asarray(K, dtype=np.float64), np.asarray(w2c, dtype=np.float64), w, h)
    if declared_size is not None and tuple(declared_size) != (w, h):
        # intrinsics given for another resolution of the same image: rescale them
        cam = Camera(cam.K, cam.w2c, int(declared_size[0]), int(declared_size[1])).resized(w, h)
    if distortion is not None:
        try:
            image, pinhole = lens.undistort(image, cam.K, distortion, background)
        except ValueError as exc:
            raise ValueError(f"{image_path}: {exc}, or ignore the distortion") from None
        cam = Camera(pinhole, cam.w2c, w, h)
    view = View(name, image, cam, depth, mask)
    return apply_scale(view, scale)


def apply_scale(view: View, scale: float) -> View:
    if scale == 1.0:
        return view
    w, h = scaled_size(view.camera.width, view.camera.height, scale)
    return resize_view(view, w, h)


def check_scale(scale: float) -> float:
    scale = float(scale)
    if not (math.isfinite(scale) and scale > 0):
        raise ValueError(f"scale must be a positive number, got {scale}")
    return scale


def check_near_far(near: float, far: float, source: str) -> tuple[float, float]:
    near, far = float(near), float(far)
    if not (math.isfinite(near) and math.isfinite(far) and 0 <= near < far):
        raise ValueError(f"invalid near/far {near}/{far} ({source}): need 0 <= near < far")
    return near, far


def resolve_background(background, default) -> tuple[float, float, float]:
    bg = default if background is None else background
    bg = tuple(float(x) for x in bg)
    if len(bg) != 3:
        raise ValueError(f"background must have 3 components, got {bg}")
    return bg  # type: ignore[return-value]


def defaults_if_present(views: dict, names: list[str]) -> list[str] | None:
    return list(names) if all(n in views for n in names) else None
