"""`scnerf-export example`: the committed example request, made from a held-out procedural scene
(validation seeds never reach training), so users without ../shared can render a view."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from PIL import Image

from .procedural import make_scene, pick_sources
from .procedural.dataset import VAL_SEED0


def camera_json(camera) -> dict:
    K = camera.K
    return {"width": int(camera.width), "height": int(camera.height),
            "intrinsics": {"fx": float(K[0, 0]), "fy": float(K[1, 1]), "cx": float(K[0, 2]), "cy": float(K[1, 2])},
            "pose": {"matrix": camera.w2c.tolist(), "kind": "world_to_camera", "axes": "opencv"}}


def write_example(out_dir: str | Path, seed: int = VAL_SEED0 + 4242, layout: str = "object",
                  width: int = 320, height: int = 256, target_index: int = 7) -> Path:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    scene = make_scene(seed, layout, n_views=16, width=width, height=height)
    sources = pick_sources(scene, target_index, gap="small")
    for i, index in enumerate(sources):
        Image.fromarray((scene.views[index].image * 255).round().astype(np.uint8)).save(out / f"source_{i}.png")
    target = scene.views[target_index]
    Image.fromarray((target.image * 255).round().astype(np.uint8)).save(out / "target_truth.png")
    request = {"sources": [{"camera": camera_json(scene.views[i].camera)} for i in sources],
               "target": camera_json(target.camera), "near": float(scene.near), "far": float(scene.far),
               "background": [0.0, 0.0, 0.0], "outputs": ["rgb"]}
    (out / "request.json").write_text(json.dumps(request, indent=2) + "\n")
    (out / "README.md").write_text(
        f"Procedural scene (layout `{layout}`, seed {seed}, a validation seed: never trained on), rendered by\n"
        f"`scnerf-export example`. Views {sources} are the sources, view {target_index} the target;\n"
        "`target_truth.png` is the ray-traced ground truth of the target view.\n")
    return out
