"""A capture folder as ``POST /v1/captures`` takes it: its camera files and images, every file a
part named ``file`` whose filename is its path in the folder. The server reads the capture with
the readers of the ``scnerf`` command line (COLMAP, nerfstudio, Blender, LLFF, DTU) and chooses its
image set; this module only keeps the upload small: of the image sets LLFF, nerfstudio and COLMAP
keep (``images/``, ``images_N/``) it sends one, the one asked for or else the largest within the
server's source limit, and when none fits it resizes the smallest here (the server scales the
cameras to the images it gets)."""

from __future__ import annotations

import io
import re
from dataclasses import dataclass
from pathlib import Path

from PIL import Image

from .errors import CaptureError

#: What a capture needs: images and camera files (the viewer's rule too).
CAPTURE_FILE = re.compile(r"\.(png|jpe?g|json|npy|txt)$", re.IGNORECASE)
IMAGE_FILE = re.compile(r"\.(png|jpe?g)$", re.IGNORECASE)
SET_FOLDER = re.compile(r"^images(?:_([1-9][0-9]*))?$")


@dataclass
class CaptureFiles:
    """The (path in the capture, bytes) to send, and what was done to keep them small."""

    files: list[tuple[str, bytes]]
    image_set: str | None
    notes: list[str]

    @property
    def bytes(self) -> int:
        return sum(len(data) for _, data in self.files)


def is_image_name(name: str) -> bool:
    """Whether a file of this name is one of a set's images: png, jpg or jpeg in any case, and not
    hidden (``._IMG_0001.JPG`` is macOS's metadata). The ``scnerf`` readers' rule too
    (scnerf_capture::readers::list_images), held with them by tests/fixtures/rules/image_files.json."""
    return bool(IMAGE_FILE.search(name)) and not name.startswith(".")


def image_sets(folder: Path) -> dict[int, Path]:
    """The image sets beside each other in ``folder``, largest first: factor -> folder (``images``
    is 1, ``images_N`` N > 1 written without leading zeros), each holding at least one image."""
    sets = {}
    for child in folder.iterdir():
        m = SET_FOLDER.match(child.name)
        if child.is_dir() and m and (m.group(1) is None or int(m.group(1)) > 1):
            if any(p.is_file() and is_image_name(p.name) for p in child.iterdir()):
                sets[int(m.group(1) or 1)] = child
    return dict(sorted(sets.items()))


def first_image_pixels(folder: Path) -> tuple[int, int]:
    """The size of a set's first image in name order."""
    first = sorted(p for p in folder.iterdir() if p.is_file() and is_image_name(p.name))[0]
    with Image.open(first) as im:
        return im.size


def choose_set(folder: Path, sets: dict[int, Path], max_source_pixels: int, downscale: int | None) -> int | None:
    """The factor of the set of ``folder`` to send (``None`` when it has no sets): ``downscale``'s,
    else the largest whose first image has at most ``max_source_pixels`` pixels, else the smallest.
    A ``downscale`` without its folder is an error naming those there are."""
    if downscale is not None:
        if max(downscale, 1) not in sets and (sets or downscale > 1):
            have = ", ".join(p.name for p in sets.values()) or "no image sets"
            raise CaptureError(
                f"downscale {downscale}: there is no images_{downscale} folder in {folder}; it has {have}"
            )
        return max(downscale, 1) if sets else None
    if not sets:
        return None
    sizes = {f: first_image_pixels(p) for f, p in sets.items()}
    fitting = [f for f in sets if sizes[f][0] * sizes[f][1] <= max_source_pixels]
    return fitting[0] if fitting else max(sets)


def collect(folder: str | Path, max_source_pixels: int, downscale: int | None = None) -> CaptureFiles:
    """The files to send of the capture in ``folder``."""
    folder = Path(folder)
    if not folder.is_dir():
        raise CaptureError(f"{folder}: no such capture folder")
    sets = image_sets(folder)
    resized: list[tuple[tuple[int, int], tuple[int, int]]] = []
    chosen = choose_set(folder, sets, max_source_pixels, downscale)
    skipped = {p for f, p in sets.items() if f != chosen}
    files = []
    for path in sorted(folder.rglob("*")):
        rel = path.relative_to(folder)
        if not path.is_file() or not CAPTURE_FILE.search(path.name) or any(p.startswith(".") for p in rel.parts):
            continue
        if any(s in path.parents for s in skipped):
            continue
        data = path.read_bytes()
        if IMAGE_FILE.search(path.name):
            data, before, after = fit(data, max_source_pixels)
            if before != after:
                resized.append((before, after))
        files.append((rel.as_posix(), data))
    if not files:
        raise CaptureError(
            f"{folder}: no capture files (images plus transforms.json, poses_bounds.npy or COLMAP files)"
        )
    return CaptureFiles(files, sets[chosen].name if chosen in sets else None, fit_note(resized, max_source_pixels))


def fit(data: bytes, max_pixels: int) -> tuple[bytes, tuple[int, int], tuple[int, int]]:
    """An image within ``max_pixels``: as it is, or resized (aspect kept, sizes rounded down as
    ``scnerf_capture::upload::fit_to_limit`` does) in its own format; with its size before and after."""
    with Image.open(io.BytesIO(data)) as im:
        w, h = im.size
        if w * h <= max_pixels:
            return data, (w, h), (w, h)
        scale = (max_pixels / (w * h)) ** 0.5
        size = (max(1, int(w * scale)), max(1, int(h * scale)))
        out = io.BytesIO()
        jpeg = im.format == "JPEG"
        im.convert("RGB" if jpeg else im.mode).resize(size, Image.Resampling.BILINEAR).save(
            out, format="JPEG" if jpeg else "PNG", **({"quality": 95} if jpeg else {})
        )
        return out.getvalue(), (w, h), size


def fit_note(resized: list[tuple[tuple[int, int], tuple[int, int]]], max_pixels: int) -> list[str]:
    """The one line the ``scnerf`` client and the server say about images resized to fit."""
    if not resized:
        return []
    (w, h), (rw, rh) = resized[0]
    return [
        f"{len(resized)} images of {w}x{h} exceed the server's limit of {max_pixels} pixels per source view: "
        f"resizing them to {rw}x{rh}"
    ]
