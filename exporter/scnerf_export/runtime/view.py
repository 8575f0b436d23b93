"""What the two Python runtimes (the PyTorch reference and ONNX Runtime) share with each other and
with the server: sources padded to the image multiple, and a view's outputs."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Rendering:
    rgb: np.ndarray  # (H,W,3) composited on the background
    depth: np.ndarray  # (H,W)
    opacity: np.ndarray  # (H,W)


def pad_images(images: np.ndarray, multiple: int, background) -> np.ndarray:
    """Pad (V,H,W,3) on the right/bottom to a multiple with the background colour; K unchanged."""
    _, h, w, _ = images.shape
    ph, pw = -h % multiple, -w % multiple
    if ph == 0 and pw == 0:
        return images
    out = np.empty((images.shape[0], h + ph, w + pw, 3), dtype=images.dtype)
    out[:] = np.asarray(background, dtype=images.dtype)
    out[:, :h, :w] = images
    return out
