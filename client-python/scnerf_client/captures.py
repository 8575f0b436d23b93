"""A capture folder as ``POST /v1/captures`` takes it: its camera files and images, every file a
part named ``file`` whose filename is its path in the folder. Which files those are, which image
set (``images/``, ``images_N/``) goes and the size each image too large for the server is resized
to are the server's choice (``POST /v1/captures/plan``, the capture readers' own rules): this
module lists the folder, reads the sizes the server asks for, and resizes as it is told."""

from __future__ import annotations

import io
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from PIL import Image, ImageOps

from .errors import CaptureError

#: EXIF orientations that turn an image by 90 degrees: its displayed width is its stored height.
TURNED = {5, 6, 7, 8}


@dataclass
class CaptureFiles:
    """The (path in the capture, bytes) to send, the image set sent, and the server's notes."""

    files: list[tuple[str, bytes]]
    image_set: str | None
    notes: list[str]

    @property
    def bytes(self) -> int:
        return sum(len(data) for _, data in self.files)


def listing(folder: Path) -> list[str]:
    """Every file under ``folder``, as its path in it with ``/`` separators."""
    return sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file())


def displayed_size(path: Path) -> tuple[int, int]:
    """An image's (width, height) as viewers show it (EXIF orientation applied), from its header."""
    with Image.open(path) as im:
        w, h = im.size
        return (h, w) if im.getexif().get(0x0112) in TURNED else (w, h)


def plan(folder: str | Path, ask: Callable[[dict[str, Any]], dict[str, Any]], downscale: int | None = None) -> dict:
    """The server's plan for ``folder`` (``ask`` posts a listing to ``POST /v1/captures/plan``):
    the listing, then, when the server asks for them, the sizes of the images it names."""
    folder = Path(folder)
    if not folder.is_dir():
        raise CaptureError(f"{folder}: no such capture folder")
    request: dict[str, Any] = {"files": listing(folder)}
    if downscale is not None:
        request["downscale"] = downscale
    answer = ask(request)
    if answer["sizes_needed"]:
        request["sizes"] = [
            dict(zip(("path", "width", "height"), (p, *displayed_size(folder / p)))) for p in answer["sizes_needed"]
        ]
        answer = ask(request)
    if answer["sizes_needed"]:
        raise CaptureError(f"{folder}: the server still asks for image sizes: {answer['sizes_needed'][:3]}")
    return answer


def collect(folder: str | Path, planned: dict) -> CaptureFiles:
    """The files ``planned`` sends of ``folder``, images resized as it says."""
    folder = Path(folder)
    files = []
    for entry in planned["send"]:
        data = (folder / entry["path"]).read_bytes()
        if "resize" in entry:
            data = resized(data, entry["resize"])
        files.append((entry["path"], data))
    return CaptureFiles(files, planned.get("image_set"), list(planned.get("notes", [])))


def resized(data: bytes, resize: dict) -> bytes:
    """The image ``data`` resized from ``resize["from"]`` to ``resize["to"]`` (as displayed, EXIF
    orientation applied) in its own format; as it is when its size is not ``from`` (the server fits
    it)."""
    with Image.open(io.BytesIO(data)) as im:
        jpeg = im.format == "JPEG"
        upright = ImageOps.exif_transpose(im)
        if upright.size != _size(resize["from"]):
            return data
        out = io.BytesIO()
        upright.convert("RGB" if jpeg else upright.mode).resize(_size(resize["to"]), Image.Resampling.BILINEAR).save(
            out, format="JPEG" if jpeg else "PNG", **({"quality": 95} if jpeg else {})
        )
        return out.getvalue()


def _size(size: dict) -> tuple[int, int]:
    return size["width"], size["height"]
