"""nerfstudio's transforms.json: per-frame or shared pinhole intrinsics, OpenGL camera-to-world poses."""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np

from .. import depth_range, lens
from ..scene import SceneData, check_near_far, check_scale, make_view, resolve_background
from .base import DataParser
from .transforms import frame_pose, frames_with_images, read_json

_NS_DISTORTION = ("k1", "k2", "k3", "k4", "p1", "p2")
_MODELS = ("OPENCV", "OPENCV_FISHEYE", "PINHOLE", "SIMPLE_PINHOLE")


class NerfstudioParser(DataParser):
    format = "nerfstudio"

    def load(
        self, path, scale: float = 1.0, background=None, near=None, far=None, ignore_distortion: bool = False
    ) -> SceneData:
        """nerfstudio transforms.json: fl_x, fl_y, cx, cy, w, h at the top level and/or per frame,
        file_path per frame, transform_matrix camera-to-world in OpenGL axes.

        nerfstudio puts the first pixel's centre at (0.5, 0.5): cx, cy are shifted by -0.5. If the
        image on disk has another size than w x h, the intrinsics are rescaled to it. Photos with
        distortion coefficients (OPENCV's k1, k2, k3, p1, p2; OPENCV_FISHEYE's k1..k4) are
        undistorted (:mod:`..lens`) unless ``ignore_distortion``; OPENCV's k4 (a term in r^8) is
        refused. near/far come from the arguments, else from 'near'/'far' (or 'near_far') keys in
        the file, else from the poses (``depth_range``).
        """
        p = Path(path)
        jf = p / "transforms.json" if p.is_dir() else p
        if not jf.exists():
            raise FileNotFoundError(f"nerfstudio transforms.json not found: {jf}")
        data = read_json(jf)
        bg = resolve_background(background, (0.0, 0.0, 0.0))
        scale = check_scale(scale)
        model = str(data.get("camera_model", "OPENCV")).upper()
        if model not in _MODELS:
            raise ValueError(f"{jf}: camera_model {model} is not supported ({', '.join(_MODELS)})")

        def distortion(fr, idx) -> lens.Distortion | None:
            """OPENCV's k1, k2, k3, p1, p2 are OpenCV's; OPENCV_FISHEYE's k1..k4 are OpenCV's fisheye
            ones. What OpenCV has no term for is refused rather than dropped."""
            k1, k2, k3, k4, p1, p2 = (
                0.0 if fr.get(key, data.get(key)) is None else param(fr, key, idx) for key in _NS_DISTORTION
            )

            def refuse(key: str, why: str) -> ValueError:
                return ValueError(f"{jf}: frame {idx} {key} is not zero: {why}")

            if model == "OPENCV_FISHEYE":
                if p1 or p2:
                    raise refuse("p1" if p1 else "p2", "OPENCV_FISHEYE has no tangential distortion")
                return lens.fisheye(k1, k2, k3, k4)
            if k4:
                raise refuse(
                    "k4", "nerfstudio's k4 of OPENCV (a term in r^8) is not supported; undistort the images first"
                )
            return lens.perspective(k1=k1, k2=k2, p1=p1, p2=p2, k3=k3)

        def param(fr, key, idx):
            v = fr.get(key, data.get(key))
            if v is None:
                raise ValueError(f"{jf}: frame {idx} has no '{key}' (neither per frame nor at the top level)")
            try:
                return float(v)
            except (TypeError, ValueError):
                raise ValueError(f"{jf}: frame {idx} '{key}' is not a number: {v!r}") from None

        entries, ignored = [], False
        for i, fr, img in frames_with_images(data, jf):
            fx = param(fr, "fl_x", i)
            fy = param(fr, "fl_y", i) if ("fl_y" in fr or "fl_y" in data) else fx
            cx, cy = param(fr, "cx", i), param(fr, "cy", i)
            w, h = int(param(fr, "w", i)), int(param(fr, "h", i))
            if fx <= 0 or fy <= 0 or w <= 0 or h <= 0:
                raise ValueError(f"{jf}: frame {i} has non-positive focal length or size")
            d = distortion(fr, i)
            if d is not None and ignore_distortion:
                if not ignored:
                    warnings.warn(f"{jf}: lens distortion ignored (images used as pinhole)", stacklevel=2)
                ignored, d = True, None
            K = np.array([[fx, 0.0, cx - 0.5], [0.0, fy, cy - 0.5], [0.0, 0.0, 1.0]])
            rel = os.path.splitext(str(fr["file_path"]))[0]
            entries.append((rel, img, K, frame_pose(fr, jf, i), (w, h), d))
        if not entries:
            raise FileNotFoundError(f"none of the frames listed in {jf} has an image file")
        stems = [Path(e[0]).name for e in entries]
        names = stems if len(set(stems)) == len(stems) else [e[0] for e in entries]
        views = {
            n: make_view(n, img, K, w2c, bg, scale, declared_size=size, distortion=d)
            for n, (_, img, K, w2c, size, d) in zip(names, entries)
        }
        nf = data.get("near_far")
        fn = data.get("near", nf[0] if isinstance(nf, (list, tuple)) and len(nf) == 2 else None)
        ff = data.get("far", nf[1] if isinstance(nf, (list, tuple)) and len(nf) == 2 else None)
        cameras = [v.camera for v in views.values()]
        n, f = check_near_far(*depth_range.resolve(near, far, (fn, ff), cameras, str(jf)), str(jf))
        return SceneData(views, n, f, bg, None, None)
