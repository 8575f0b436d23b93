"""`scnerf-export example`: the committed example request, a photo-like procedural tabletop scene
from a validation seed (never trained on), so users without ../shared can render a view.

Sources are 640x512, the resolution the default model's backbone was trained at; the target is
rendered smaller so that a first render takes under a minute on two cores. Its ground truth is
ray-traced at the target's own size."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from PIL import Image

from ..cameras import camera_json
from .procedural import make_scene, pick_sources
from .procedural.dataset import VAL_SEED0
from .procedural.layouts import build_layout
from .procedural.raytrace import render_view

EXAMPLE_SEED = VAL_SEED0 + 4242


def save_png(image: np.ndarray, path: Path) -> None:
    Image.fromarray((image * 255).round().astype(np.uint8)).save(path)


def write_example(
    out_dir: str | Path,
    seed: int = EXAMPLE_SEED,
    layout: str = "tabletop",
    width: int = 640,
    height: int = 512,
    target_index: int = 11,
    target_scale: float = 0.375,
    views: int = 16,
) -> Path:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    scene = make_scene(seed, layout, n_views=views, width=width, height=height)
    sources = pick_sources(scene, target_index, gap="small")
    for i, index in enumerate(sources):
        save_png(scene.views[index].image, out / f"source_{i}.png")
    world, _, _, _ = build_layout(seed, layout, views, width, height)
    target = scene.views[target_index].camera.scaled(target_scale)
    save_png(render_view(world, target, supersample=scene.meta["supersample"]).image, out / "target_truth.png")
    request = {
        "sources": [{"camera": camera_json(scene.views[i].camera)} for i in sources],
        "target": camera_json(target),
        "near": float(scene.near),
        "far": float(scene.far),
        "background": [0.0, 0.0, 0.0],
        "outputs": ["rgb"],
    }
    (out / "request.json").write_text(json.dumps(request, indent=2) + "\n")
    (out / "README.md").write_text(
        f"A procedural tabletop scene (layout `{layout}`, seed {seed}: a validation seed, never trained on),\n"
        f"written by `scnerf-export example`. Views {sources} of {views} ({width}x{height}) are the sources,\n"
        f"the 3 nearest to view {target_index}, the target, asked for at {target.width}x{target.height}.\n"
        "`target_truth.png` is the ray-traced ground truth of the target view at that size.\n"
    )
    return out
