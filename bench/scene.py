"""The benchmark scene: the committed example's procedural tabletop (a validation seed), rendered
at any size from the same cameras, cached on disk; and the inputs the measurements read from it."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
from PIL import Image

from scnerf_export import cameras as cams
from scnerf_export.cameras import camera_from_json, camera_json
from scnerf_export.data.procedural.dataset import VAL_SEED0
from scnerf_export.data.procedural.layouts import build_layout
from scnerf_export.data.procedural.raytrace import render_view
from scnerf_export.data.procedural.scenes import pick_camera_sources

# The cameras of a layout do not depend on the image size, so every size shows the same view.
SCENE_SEED_OFFSET, SCENE_LAYOUT, SCENE_VIEWS, SCENE_TARGET = 4242, "tabletop", 16, 7


def parse_sizes(text: str) -> list[tuple[int, int]]:
    """'160x128,320x256' -> [(160, 128), (320, 256)] (width, height)."""
    return [tuple(int(x) for x in s.lower().split("x")) for s in text.split(",") if s.strip()]


def make_scene_dir(root: Path, width: int, height: int) -> Path:
    """Sources, request.json and ground truth of the benchmark scene at one size (cached on disk)."""
    seed = VAL_SEED0 + SCENE_SEED_OFFSET
    out = root / f"{SCENE_LAYOUT}-{seed}-{width}x{height}"
    if (out / "request.json").is_file():
        return out
    out.mkdir(parents=True, exist_ok=True)
    world, cameras, near, far = build_layout(seed, SCENE_LAYOUT, SCENE_VIEWS, width, height)
    sources = pick_camera_sources(cameras, SCENE_TARGET, gap="small")
    for k, index in enumerate(sources + [SCENE_TARGET]):
        view = render_view(world, cameras[index], supersample=2)
        name = f"source_{k}.png" if k < len(sources) else "target_truth.png"
        Image.fromarray((view.image * 255).round().astype("uint8")).save(out / name)
    request = {
        "sources": [{"camera": camera_json(cameras[i])} for i in sources],
        "target": camera_json(cameras[SCENE_TARGET]),
        "near": float(near),
        "far": float(far),
        "background": [0.0, 0.0, 0.0],
        "outputs": ["rgb"],
    }
    (out / "request.json").write_text(json.dumps(request, indent=2) + "\n")
    return out


def load_png(path: Path) -> np.ndarray:
    return np.asarray(Image.open(path).convert("RGB"), dtype=np.float32) / 255.0


def read_scene(scene_dir: Path):
    """Decode the source PNGs (timed: the 'decode' stage) and the cameras."""
    request = json.loads((scene_dir / "request.json").read_text())
    start = time.perf_counter()
    images = np.stack([load_png(scene_dir / f"source_{i}.png") for i in range(len(request["sources"]))])
    decode = time.perf_counter() - start
    cameras = [camera_from_json(s["camera"]) for s in request["sources"]]
    return request, images, cameras, camera_from_json(request["target"]), decode


def renderer_run_feeds(bundle, scene_dir: Path, rays) -> dict:
    """The renderer's inputs for the target view's rays ``rays`` (a slice or pixel indices, row-major)."""
    request, images, cameras, target, _ = read_scene(scene_dir)
    near, far = request["near"], request["far"]
    scene = bundle.encode_scene(images, cameras, near, far, tuple(request["background"]))
    origins, directions = cams.target_rays(target)
    return bundle.renderer_feeds(scene, origins[rays], directions[rays], near, far, (near, far))
