"""What `scnerf-export refine` reads of a capture: the folder in its format (detected as the Rust
readers detect it, ``capture/src/readers/mod.rs``), the image set and size the server would use
(``capture/src/image_sets.rs``, ``upload::fit_to_limit``), which views are held out, each view's
three sources (the server's rule: the nearest by camera centre, ``cameras.rank_sources``) and a
hash that names what was read.

The views are read by the exporter's parsers (:mod:`scnerf_export.data.dataparsers`), the ones
``scnerf-export eval`` reads. Like the Rust readers, they read COLMAP's text and binary models and
undistort photos (``data.lens``).
"""

from __future__ import annotations

import hashlib
import json
import math
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..data import datasets
from ..data.dataparsers.colmap import find_model
from ..data.scene import SceneData, image_size, list_images, resize_view

# The server's --max-source-pixels (server/src/request/mod.rs, Limits::default).
MAX_SOURCE_PIXELS = 1024 * 1024
# Views held out when neither the command nor the capture names them: LLFF's every 8th.
DEFAULT_HOLDOUT = 8
# Training views set aside for validation when the command names none: 1 in 8, at least one.
DEFAULT_VALIDATION = 8
# A training view is rendered from 3 other training views; one view at least is held out and one
# is a validation view.
SOURCES = 3
MIN_VIEWS = SOURCES + 3


class CaptureError(ValueError):
    """A capture refine cannot use; the message is one line, fit for a CLI."""


# ------------------------------------------------------------------------------------------- format


def _is_blender_json(path: Path) -> bool:
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise CaptureError(f"{path}: cannot read ({exc})") from None
    return isinstance(data, dict) and "camera_angle_x" in data and "fl_x" not in data


def detect_format(path: Path) -> str:
    """The capture's format, by the files it has (the Rust readers' ``detect``)."""
    if path.is_file():
        if path.suffix == ".json":
            return "blender" if _is_blender_json(path) else "nerfstudio"
        raise CaptureError(f"{path}: not a capture folder or transforms JSON file")
    if not path.is_dir():
        raise CaptureError(f"{path}: no such capture folder")
    if (path / "poses_bounds.npy").is_file():
        return "llff"
    if (path / "Cameras").is_dir():
        return "dtu"
    if any((path / f"transforms_{s}.json").is_file() for s in ("train", "val", "test")):
        return "blender"
    if (path / "transforms.json").is_file():
        return "blender" if _is_blender_json(path / "transforms.json") else "nerfstudio"
    if find_model(path) is not None:
        return "colmap"
    raise CaptureError(
        f"{path}: cannot tell the capture format: expected poses_bounds.npy (LLFF), Cameras/ (DTU), "
        "transforms_*.json (Blender), transforms.json (nerfstudio) or a COLMAP model"
    )


# ---------------------------------------------------------------------------------------- image sets


@dataclass(frozen=True)
class ImageSet:
    """``images/`` (factor 1) or ``images_N/``, with the size of its first image."""

    factor: int
    width: int
    height: int

    def describe(self) -> str:
        folder = "images" if self.factor == 1 else f"images_{self.factor}"
        return f"{folder} ({self.width}x{self.height})"


def _set_factor(name: str) -> int | None:
    if name == "images":
        return 1
    digits = name.removeprefix("images_")
    return (
        int(digits) if digits != name and digits.isdigit() and str(int(digits)) == digits and int(digits) > 1 else None
    )


def image_sets(root: Path, fmt: str) -> list[ImageSet]:
    """The capture's image sets, largest first; none for formats that do not keep them."""
    if fmt not in ("llff", "nerfstudio", "colmap") or not root.is_dir():
        return []
    sets = []
    for folder in sorted(root.iterdir()):
        factor = _set_factor(folder.name) if folder.is_dir() else None
        images = list_images(folder) if factor else []
        if images:
            sets.append(ImageSet(factor, *image_size(images[0])))
    return sorted(sets, key=lambda s: s.factor)


def pick_image_set(sets: list[ImageSet], downscale: int | None, max_pixels: int) -> ImageSet | None:
    """``--downscale N``'s set, or the largest set within ``max_pixels`` (the smallest if none is)."""
    if not sets:
        if downscale not in (None, 1):
            raise CaptureError(f"--downscale {downscale}: the capture keeps no images_N folders")
        return None
    if downscale is not None:
        found = [s for s in sets if s.factor == max(downscale, 1)]
        if not found:
            have = ", ".join(s.describe() for s in sets)
            raise CaptureError(
                f"--downscale {downscale}: there is no images_{downscale} folder; the capture has {have}"
            )
        return found[0]
    return next((s for s in sets if s.width * s.height <= max_pixels), sets[-1])


def fit_to_limit(scene: SceneData, max_pixels: int) -> str | None:
    """Shrinks every view of more than ``max_pixels`` pixels to fit, as the server does (aspect
    kept, the size rounded down); what was done, if anything."""
    over = [name for name, v in scene.views.items() if v.camera.width * v.camera.height > max_pixels]
    for name in over:
        view = scene.views[name]
        scale = math.sqrt(max_pixels / (view.camera.width * view.camera.height))
        width, height = max(1, int(view.camera.width * scale)), max(1, int(view.camera.height * scale))
        scene.views[name] = resize_view(view, width, height)
    if not over:
        return None
    first = scene.views[over[0]].camera
    return f"{len(over)} views exceed {max_pixels} pixels: resized to {first.width}x{first.height}"


# ------------------------------------------------------------------------------------------- capture


@dataclass
class Capture:
    """A capture as refine uses it: its views, where they came from and the hash of what was read."""

    path: Path
    format: str
    scene: SceneData
    image_set: str | None
    sha256: str

    @property
    def size(self) -> tuple[int, int]:
        camera = next(iter(self.scene.views.values())).camera
        return camera.width, camera.height

    def describe(self) -> dict:
        width, height = self.size
        return {
            "folder": self.path.name,
            "format": self.format,
            "sha256": self.sha256,
            "views": len(self.scene.views),
            "image_set": self.image_set,
            "size": [width, height],
            "near": self.scene.near,
            "far": self.scene.far,
        }


def capture_sha256(scene: SceneData) -> str:
    """Names what was read: each view's name, pixels (float32 RGB) and camera, and near/far."""
    h = hashlib.sha256()
    for name in sorted(scene.views):
        view = scene.views[name]
        h.update(name.encode())
        h.update(np.ascontiguousarray(view.image, dtype=np.float32).tobytes())
        h.update(np.ascontiguousarray(view.camera.K, dtype=np.float64).tobytes())
        h.update(np.ascontiguousarray(view.camera.w2c, dtype=np.float64).tobytes())
    h.update(np.array([scene.near, scene.far], dtype=np.float64).tobytes())
    return h.hexdigest()


def read_capture(
    path: str | Path,
    fmt: str | None = None,
    downscale: int | None = None,
    max_pixels: int = MAX_SOURCE_PIXELS,
    near: float | None = None,
    far: float | None = None,
    ignore_distortion: bool = False,
) -> Capture:
    """The capture at ``path`` read as the server reads an uploaded one: its format, the image set
    ``pick_image_set`` chooses, photos undistorted (unless ``ignore_distortion``, the client's
    ``--ignore-distortion``), views over ``max_pixels`` shrunk to fit."""
    root = Path(path)
    fmt = fmt or detect_format(root)
    chosen = pick_image_set(image_sets(root, fmt), downscale, max_pixels)
    scale = 1.0 / chosen.factor if chosen else 1.0
    scene = datasets.load_scene(root, fmt, scale=scale, near=near, far=far, ignore_distortion=ignore_distortion)
    resized = fit_to_limit(scene, max_pixels)
    if resized:
        warnings.warn(f"{root}: {resized} (the server's source limit)", stacklevel=2)
    return Capture(root, fmt, scene, chosen.describe() if chosen else None, capture_sha256(scene))


# --------------------------------------------------------------------------------------------- split


@dataclass(frozen=True)
class Split:
    """Which views train, which choose the kept step (validation) and which are held out for the
    record; each view's sources, all training views."""

    training: list[str]
    validation: list[str]
    held_out: list[str]
    sources: dict[str, list[str]]


def held_out_names(scene: SceneData, holdout: int | None, targets: list[str] | None) -> list[str]:
    """``targets``; else every ``holdout``-th view; else the capture's own targets (lego's val views,
    DTU's test views, LLFF's every 8th); else every 8th view."""
    names = list(scene.views)
    if targets:
        return named_views(scene, targets, "--targets")
    if holdout is not None:
        if holdout < 2:
            raise CaptureError(f"--holdout {holdout}: hold out every K-th view with K >= 2")
        return names[::holdout]
    return list(scene.default_targets or names[::DEFAULT_HOLDOUT])


def named_views(scene: SceneData, names: list[str], flag: str) -> list[str]:
    """``names`` (the views a flag names), each once; an error naming the flag for any the capture lacks."""
    unknown = [n for n in names if n not in scene.views]
    if unknown:
        raise CaptureError(f"{flag}: {', '.join(unknown)} not in the capture (views: {', '.join(scene.views)})")
    return list(dict.fromkeys(names))


def validation_names(scene: SceneData, pool: list[str], held: list[str], chosen: list[str] | None) -> list[str]:
    """``chosen``, none of them held out; else 1 in ``DEFAULT_VALIDATION`` of the views ``pool``
    left after the hold-out, at least one, spaced evenly through it."""
    if chosen:
        names = named_views(scene, chosen, "--validation")
        both = [n for n in names if n in held]
        if both:
            raise CaptureError(f"--validation: {', '.join(both)} held out; a validation view must be a training view")
        return names
    count = max(1, len(pool) // DEFAULT_VALIDATION)
    return [pool[(2 * i + 1) * len(pool) // (2 * count)] for i in range(count)]


def _nearest(scene: SceneData, name: str, pool: list[str]) -> list[str] | None:
    try:
        return datasets.nearest_sources(scene, name, pool, SOURCES)
    except ValueError:
        return None


def _too_few_to_train(count: int, held: list[str], validation: list[str], left: int) -> str:
    return (
        f"no views left to train on: holding out {len(held)} and validating on {len(validation)} of {count} "
        f"views leaves {left}; each training view is rendered from {SOURCES} other training views, "
        f"so refine needs {SOURCES + 1}"
    )


def split_views(
    scene: SceneData,
    holdout: int | None = None,
    targets: list[str] | None = None,
    validation: list[str] | None = None,
) -> Split:
    """The capture's training, validation and held-out views, disjoint. Only training views are
    sources: every view is rendered from the 3 training views nearest to it, so neither a
    validation view nor a held-out one reaches a training ray."""
    count = len(scene.views)
    if count < MIN_VIEWS:
        raise CaptureError(
            f"the capture has {count} views; refine needs at least {MIN_VIEWS} (each training view is "
            f"rendered from {SOURCES} others, one view at least is held out and one validates)"
        )
    held = held_out_names(scene, holdout, targets)
    if not held:
        raise CaptureError("no view is held out: refine reports the kept model's PSNR on held-out views")
    rest = [n for n in scene.views if n not in held]
    checks = validation_names(scene, rest, held, validation)
    pool = [n for n in rest if n not in checks]
    if len(pool) < SOURCES + 1:
        raise CaptureError(_too_few_to_train(count, held, checks, len(pool)))
    sources = {name: _nearest(scene, name, pool) for name in scene.views}
    missing = [n for n, s in sources.items() if s is None]
    if missing:
        warnings.warn(
            f"left out, fewer than {SOURCES} training views face their way: {', '.join(missing)}", stacklevel=2
        )
    training = [n for n in pool if sources[n] is not None]
    checks = [n for n in checks if sources[n] is not None]
    held = [n for n in held if sources[n] is not None]
    if not training:
        raise CaptureError(f"no views left to train on: no training view has {SOURCES} others facing its way")
    for kind, names in (("validation", checks), ("held-out", held)):
        if not names:
            raise CaptureError(f"no {kind} view has {SOURCES} training views facing its way")
    return Split(training, checks, held, {n: s for n, s in sources.items() if s is not None})


def spread_order(scene: SceneData, names: list[str]) -> list[str]:
    """``names`` ordered so that every prefix spreads over the capture: the view nearest the
    centroid of the camera centres first, then each time the view farthest from those before it
    (a refinement stopped early has trained on views from all around)."""
    centres = np.stack([scene.views[n].camera.center for n in names])
    first = int(np.argmin(np.linalg.norm(centres - centres.mean(axis=0), axis=1)))
    order, distance = [first], np.linalg.norm(centres - centres[first], axis=1)
    distance[first] = -1.0
    while len(order) < len(names):
        nxt = int(np.argmax(distance))
        order.append(nxt)
        distance = np.minimum(distance, np.linalg.norm(centres - centres[nxt], axis=1))
        distance[order] = -1.0
    return [names[i] for i in order]


# ------------------------------------------------------------------------------------- a test capture


def write_procedural_capture(folder: str | Path, views: int = 9, width: int = 64, height: int = 48, seed: int = 11):
    """A small capture to try refine on (tests, docker/verify.sh): ``views`` views of a procedural
    object scene (:mod:`scnerf_export.data.procedural`) as a nerfstudio folder, transforms.json
    (with near/far) and PNGs. Returns the folder."""
    from PIL import Image

    from ..cameras import opencv_w2c_to_opengl_c2w
    from ..data.procedural import make_scene

    root = Path(folder)
    (root / "images").mkdir(parents=True)
    scene = make_scene(seed, "object", n_views=views, width=width, height=height)
    frames = []
    for i, view in enumerate(scene.views):
        Image.fromarray((np.clip(view.image, 0, 1) * 255).round().astype(np.uint8)).save(root / f"images/v{i}.png")
        K = view.camera.K
        frames.append(
            {
                "file_path": f"images/v{i}.png",
                "transform_matrix": opencv_w2c_to_opengl_c2w(view.camera.w2c, np.linalg.inv).tolist(),
                "fl_x": K[0, 0],
                "fl_y": K[1, 1],
                "cx": K[0, 2] + 0.5,  # nerfstudio's first pixel centre is at (0.5, 0.5)
                "cy": K[1, 2] + 0.5,
                "w": width,
                "h": height,
            }
        )
    data = {"camera_model": "PINHOLE", "near": scene.near, "far": scene.far, "frames": frames}
    (root / "transforms.json").write_text(json.dumps(data, indent=1) + "\n")
    return root
