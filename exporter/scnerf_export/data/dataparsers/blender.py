"""NeRF-synthetic ("Blender") scenes: transforms_{train,val,test}.json and RGBA images."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

from ..scene import (
    SceneData,
    View,
    check_near_far,
    check_scale,
    defaults_if_present,
    image_size,
    make_view,
    resolve_background,
)
from .base import DataParser
from .transforms import frame_pose, frames_with_images, read_json

LEGO_DEFAULT_SOURCES = ["r_6", "r_43", "r_33"]
LEGO_DEFAULT_TARGETS = ["r_63", "r_70", "r_18", "r_28"]
BLENDER_NEAR_FAR = (2.0, 6.0)


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


class BlenderParser(DataParser):
    format = "blender"

    def load(
        self, path, scale: float = 1.0, background=None, near=None, far=None, ignore_distortion: bool = False
    ) -> SceneData:
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
            json_files = [
                p / f"transforms_{s}.json" for s in ("train", "val", "test") if (p / f"transforms_{s}.json").exists()
            ]
            if not json_files and (p / "transforms.json").exists():
                json_files = [p / "transforms.json"]
            if not json_files:
                raise FileNotFoundError(f"no transforms_{{train,val,test}}.json or transforms.json in {p}")
        else:
            raise FileNotFoundError(f"Blender scene not found: {p}")

        bg = resolve_background(background, (1.0, 1.0, 1.0))
        scale = check_scale(scale)
        entries = []  # (split, stem, image_path, w2c, camera_angle_x, camera_angle_y)
        for jf in json_files:
            data = read_json(jf)
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
            for i, fr, img in frames_with_images(data, jf):
                entries.append((split, img.stem, img, frame_pose(fr, jf, i), angle_x, angle_y))
        if not entries:
            listed = [j.name for j in json_files]
            raise FileNotFoundError(
                f"none of the frames listed in {listed} has an image file under {json_files[0].parent}"
            )
        names = _unique_names([(e[0], e[1]) for e in entries])
        views: dict[str, View] = {}
        for name, (_, _, img, w2c, ax, ay) in zip(names, entries):
            w, h = image_size(img)
            fx = 0.5 * w / math.tan(0.5 * ax)
            fy = fx if ay is None else 0.5 * h / math.tan(0.5 * ay)
            K = np.array([[fx, 0.0, w / 2.0], [0.0, fy, h / 2.0], [0.0, 0.0, 1.0]])
            views[name] = make_view(name, img, K, w2c, bg, scale)
        n = BLENDER_NEAR_FAR[0] if near is None else near
        f = BLENDER_NEAR_FAR[1] if far is None else far
        n, f = check_near_far(n, f, str(p))
        return SceneData(
            views,
            n,
            f,
            bg,
            defaults_if_present(views, LEGO_DEFAULT_SOURCES),
            defaults_if_present(views, LEGO_DEFAULT_TARGETS),
        )
