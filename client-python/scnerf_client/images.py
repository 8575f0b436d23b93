"""Source images as the server takes them (PNG or JPEG bytes) and rendered outputs as numpy
arrays."""

from __future__ import annotations

import base64
import io
from pathlib import Path
from typing import Union

import numpy as np
from PIL import Image

ImageLike = Union[np.ndarray, Image.Image, bytes, str, Path]


def encoded(image: ImageLike) -> tuple[bytes, str]:
    """PNG or JPEG bytes and their content type: a file or encoded bytes as they are; an array
    ((H, W, 3|4), uint8, or float in [0, 1]) or a PIL image as PNG."""
    if isinstance(image, (str, Path)):
        image = Path(image).read_bytes()
    if isinstance(image, bytes):
        return image, "image/jpeg" if image[:2] == b"\xff\xd8" else "image/png"
    if isinstance(image, np.ndarray):
        array = image if image.dtype == np.uint8 else (np.clip(image, 0.0, 1.0) * 255.0).round().astype(np.uint8)
        image = Image.fromarray(array)
    out = io.BytesIO()
    image.save(out, format="PNG")
    return out.getvalue(), "image/png"


def decode_rgb(data_b64: str) -> np.ndarray:
    """The answer's base64 PNG as an (H, W, 3) float32 array in [0, 1]."""
    with Image.open(io.BytesIO(base64.b64decode(data_b64))) as im:
        return np.asarray(im.convert("RGB"), np.float32) / 255.0


def decode_floats(data_b64: str, height: int, width: int) -> np.ndarray:
    """The answer's base64 little-endian float32 map as an (H, W) array."""
    return np.frombuffer(base64.b64decode(data_b64), dtype="<f4").reshape(height, width).copy()
