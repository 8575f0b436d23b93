"""nerfstudio's transforms.json: per-frame or shared pinhole intrinsics, OpenGL camera-to-world poses."""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np

from .. import depth_range
from ..scene import SceneData, check_near_far, check_scale, make_view, resolve_background
from .base import DataParser
from .transforms import frame_pose, frames_with_images, read_json

_NS_DISTORTION = ("k1", "k2", "k3", "k4", "p1", "p2")


class NerfstudioParser(DataParser):
    format = "nerfstudio"

    def load(self, path, scale: float = 1.0, background=None, near=None, far=None) -> SceneData:
        """nerfstudio transforms.json: fl_x, fl_y, cx, cy, w, h at the top level and/or per frame,
        file_path per frame, transform_matrix camera-to-world in OpenGL axes.

        nerfstudio puts the first pixel's centre at (0.5, 0.5): cx, cy are shifted by -0.5. If the
        image on disk has another size than w x h, the intrinsics are rescaled to it. Distortion
        coefficients are ignored (with a warning). near/far come from the arguments, else from
        'near'/'far' (or 'near_far') keys in the file, else from the poses (``depth_range``).
        """
        p = Path(path)
        jf = p / "transforms.json" if p.is_dir() else p
        if not jf.exists():
            raise FileNotFoundError(f"nerfstudio transforms.json not found: {jf}")
        data = read_json(jf)
        bg = resolve_background(background, (0.0, 0.0, 0.0))
        scale = check_scale(scale)
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
        for i, fr, img in frames_with_images(data, jf):
            fx = param(fr, "fl_x", i)
            fy = param(fr, "fl_y", i) if ("fl_y" in fr or "fl_y" in data) else fx
            cx, cy = param(fr, "cx", i), param(fr, "cy", i)
            w, h = int(param(fr, "w", i)), int(param(fr, "h", i))
            if fx <= 0 or fy <= 0 or w <= 0 or h <= 0:
                raise ValueError(f"{jf}: frame {i} has non-positive focal length or size")
            if not warned and any(abs(float(fr.get(k, data.get(k, 0.0)) or 0.0)) > 0 for k in _NS_DISTORTION):
                warnings.warn(
                    f"{jf}: lens distortion coefficients are ignored (images are used as pinhole)", stacklevel=2
                )
                warned = True
            K = np.array([[fx, 0.0, cx - 0.5], [0.0, fy, cy - 0.5], [0.0, 0.0, 1.0]])
            rel = os.path.splitext(str(fr["file_path"]))[0]
            entries.append((rel, img, K, frame_pose(fr, jf, i), (w, h)))
        if not entries:
            raise FileNotFoundError(f"none of the frames listed in {jf} has an image file")
        stems = [Path(e[0]).name for e in entries]
        names = stems if len(set(stems)) == len(stems) else [e[0] for e in entries]
        views = {
            n: make_view(n, img, K, w2c, bg, scale, declared_size=size)
            for n, (_, img, K, w2c, size) in zip(names, entries)
        }
        nf = data.get("near_far")
        fn = data.get("near", nf[0] if isinstance(nf, (list, tuple)) and len(nf) == 2 else None)
        ff = data.get("far", nf[1] if isinstance(nf, (list, tuple)) and len(nf) == 2 else None)
        cameras = [v.camera for v in views.values()]
        n, f = check_near_far(*depth_range.resolve(near, far, (fn, ff), cameras, str(jf)), str(jf))
        return SceneData(views, n, f, bg, None, None)
