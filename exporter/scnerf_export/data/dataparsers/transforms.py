"""transforms.json, the file the Blender (NeRF-synthetic) and nerfstudio formats share: reading it,
finding its frames' images and their poses (camera-to-world, OpenGL axes)."""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from ...cameras import opengl_c2w_to_opencv_w2c
from ..scene import IMAGE_EXTENSIONS, is_image


def read_json(path: Path) -> dict:
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
    if not is_image(p):
        for ext in IMAGE_EXTENSIONS + tuple(e.upper() for e in IMAGE_EXTENSIONS):
            q = p.with_name(p.name + ext)
            if q.exists():
                return q
    return None


def frames_with_images(data: dict, json_path: Path) -> Iterator[tuple[int, dict, Path]]:
    """(index, frame, image file) of every frame whose image exists; frames without one are skipped."""
    for i, frame in enumerate(data["frames"]):
        if not isinstance(frame, dict) or "file_path" not in frame:
            raise ValueError(f"{json_path}: frame {i} has no 'file_path'")
        image = _resolve_image(json_path.parent, str(frame["file_path"]))
        if image is not None:
            yield i, frame, image


def frame_pose(frame: dict, json_path: Path, idx: int) -> np.ndarray:
    try:
        m = np.asarray(frame["transform_matrix"], dtype=np.float64)
    except (KeyError, TypeError, ValueError):
        raise ValueError(f"{json_path}: frame {idx} has no valid 'transform_matrix'") from None
    if m.shape not in ((4, 4), (3, 4)) or not np.all(np.isfinite(m)):
        raise ValueError(
            f"{json_path}: frame {idx} 'transform_matrix' must be a finite 4x4 matrix, got shape {m.shape}"
        )
    return opengl_c2w_to_opencv_w2c(m)
