"""`python -m bench.few_samples`: can the fine renderer learn to render from K samples what the
renderer renders from all S?

A distillation experiment, on procedural scenes only (the real scenes score it, never train it).
The default bundle's renderer is read back into PyTorch (``renderer_state_from_current_graph``);
for ``--scenes`` procedural training scenes (320x256, ``--targets`` targets each, their 3 nearest
views as sources) ONNX Runtime's guide graph renders 1,024 random rays at all S samples: the
teacher's colours, opacities, weights and rectifier heads. Then M2, the rectifiers and M4 (M1
frozen, as in the default's training) are trained for ``--minutes`` so that each ray rendered at
its K heaviest samples (``select_samples`` on its own weights, with multiplicities: a perfect
sampler) gives the teacher's colour and opacity. Scored before and after on ``--pixels`` random
pixels of each real scene of ``bench.sampling`` at 320x256 (with the nearest level-0 ray's heads,
as the server renders them): the share beyond 0.25 from full sampling in a channel, and the mean
error.

    .venv/bin/python -m bench.few_samples --samples 4 --minutes 12
"""

from __future__ import annotations

import argparse
import copy
import os
import time
from pathlib import Path

import numpy as np
import torch

from scnerf_export import cameras as cams
from scnerf_export.data.procedural.dataset import ProceduralDataset
from scnerf_export.export.reexport import renderer_state_from_current_graph
from scnerf_export.model.network import SCNeRF
from scnerf_export.model.renderer import RayRenderer
from scnerf_export.runtime import guided
from scnerf_export.runtime.onnx_pipeline import OnnxBundle

from .sampling import SCENES, encoded_target, write_results

SPECKLE = 0.25
SIZE = (320, 256)
TEACHER_RAYS = 1024


def tensor(a) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(a))


def scene_inputs(encoded: dict, near: float, far: float) -> dict:
    """The renderer's per-scene inputs as tensors."""
    near_far = torch.tensor([near, far], dtype=torch.float32)
    names = ("volume", "images", "features", "intrinsics", "extrinsics")
    return {"near_far": near_far, **{n: tensor(encoded[n]) for n in names}}


def teacher_rays(bundle: OnnxBundle, encoded: dict, origins, directions, near: float, far: float) -> dict:
    """The guide graph's outputs for the rays: the teacher's rgb, opacity, weights and heads."""
    guide, _ = bundle.guided_runs(encoded, near, far)
    out = guide(origins, directions)
    heads = {k.removesuffix("_heads"): tensor(v) for k, v in out.items() if k.endswith("_heads")}
    return {"rgb": tensor(out["rgb"]), "opacity": tensor(out["opacity"]), "weights": out["weights"], "heads": heads}


def procedural_examples(bundle: OnnxBundle, scenes: int, targets: int, cache: Path, rng) -> list[dict]:
    data = ProceduralDataset(
        "train", n_scenes=scenes, n_views=10, width=SIZE[0], height=SIZE[1], cache_dir=cache, memory_scenes=2
    )
    found = []
    for index in range(scenes):
        for target in rng.choice(10, targets, replace=False):
            ex = data.example(index, int(target), "small")
            images = np.stack([v.image for v in ex.sources]).astype(np.float32)
            encoded = bundle.encode_scene(images, [v.camera for v in ex.sources], ex.near, ex.far, (0, 0, 0))
            origins, directions = cams.target_rays(ex.target.camera)
            rows = rng.choice(len(origins), TEACHER_RAYS, replace=False)
            teacher = teacher_rays(bundle, encoded, origins[rows], directions[rows], ex.near, ex.far)
            rays = {"origins": tensor(origins[rows]), "directions": tensor(directions[rows])}
            found.append({**rays, **scene_inputs(encoded, ex.near, ex.far), "teacher": teacher})
    return found


def render_at_heaviest(renderer: RayRenderer, ex: dict, rows: np.ndarray, k: int, threshold: float, heads: dict):
    """The rays ``rows`` of ``ex`` at their own K heaviest samples."""
    index, multiplicity, _ = guided.select_samples(ex["teacher"]["weights"][rows], k, threshold)
    r = tensor(rows)
    return renderer.render_samples(
        ex["origins"][r],
        ex["directions"][r],
        tensor(index.astype(np.float32)),
        tensor(multiplicity),
        ex["near_far"],
        ex["near_far"],
        ex["volume"],
        ex["images"],
        ex["features"],
        ex["intrinsics"],
        ex["extrinsics"],
        heads,
    )


def train(renderer: RayRenderer, examples: list[dict], k: int, threshold: float, minutes: float, lr: float, rng):
    for name, p in renderer.named_parameters():
        p.requires_grad = not name.startswith("m1.")
    optimiser = torch.optim.Adam([p for p in renderer.parameters() if p.requires_grad], lr=lr)
    start, steps, losses = time.monotonic(), 0, []
    while time.monotonic() - start < minutes * 60:
        ex = examples[int(rng.integers(len(examples)))]
        rows = np.sort(rng.choice(TEACHER_RAYS, 256, replace=False))
        heads = {n: h[tensor(rows)] for n, h in ex["teacher"]["heads"].items()}
        out = render_at_heaviest(renderer, ex, rows, k, threshold, heads)
        r = tensor(rows)
        loss = (out.rgb - ex["teacher"]["rgb"][r]).abs().mean() + (
            out.opacity - ex["teacher"]["opacity"][r]
        ).abs().mean()
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        steps += 1
        losses.append(float(loss.detach()))
    return {"steps": steps, "first_loss": float(np.mean(losses[:50])), "last_loss": float(np.mean(losses[-50:]))}


def real_view(bundle: OnnxBundle, name: str, pixels: int) -> dict:
    """``pixels`` random pixels of a real scene's view: full sampling's colours and weights, and
    the heads of each pixel's nearest level-0 ray."""
    scene, encoded, camera = encoded_target(bundle, name, *SIZE)
    width, height = SIZE
    origins, directions = cams.target_rays(camera)
    rng = np.random.default_rng(0)
    rows = np.sort(rng.choice(width * height, pixels, replace=False))
    full = teacher_rays(bundle, encoded, origins[rows], directions[rows], scene.near, scene.far)
    step = bundle.policy.step
    first = guided.first_level_pixels(width, height, step)
    level0 = first[:, 0] * width + first[:, 1]
    guides = teacher_rays(bundle, encoded, origins[level0], directions[level0], scene.near, scene.far)
    nearest = guided.nearest_guide(
        np.stack([rows // width, rows % width], axis=1), (width - 1) // step + 1, (height - 1) // step + 1, step
    )
    heads = {n: h[tensor(nearest.astype(np.int64))] for n, h in guides["heads"].items()}
    rays = {"origins": tensor(origins[rows]), "directions": tensor(directions[rows])}
    background = torch.tensor(scene.background, dtype=torch.float32)
    return {
        **rays,
        **scene_inputs(encoded, scene.near, scene.far),
        "teacher": full,
        "heads": heads,
        "background": background,
        "name": name,
    }


def score(renderer: RayRenderer, view: dict, k: int, threshold: float) -> dict:
    rows = np.arange(len(view["origins"]))
    with torch.no_grad():
        out = render_at_heaviest(renderer, view, rows, k, threshold, view["heads"])
    bg = view["background"]
    full = view["teacher"]["rgb"] + (1 - view["teacher"]["opacity"])[:, None] * bg
    error = (out.rgb + (1 - out.opacity)[:, None] * bg - full).abs()
    return {
        "mean_abs_error": float(error.mean()),
        "beyond_0_25_pct": float(100 * (error.max(dim=1).values > SPECKLE).float().mean()),
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--bundle", type=Path, default=Path("bundles/default"))
    p.add_argument("--samples", type=int, default=4)
    p.add_argument("--minutes", type=float, default=12.0)
    p.add_argument("--lr", type=float, default=1e-4)
    p.add_argument("--scenes", type=int, default=12)
    p.add_argument("--targets", type=int, default=2)
    p.add_argument("--pixels", type=int, default=4000)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--cache", type=Path, default=Path(__file__).parent / ".cache" / "procedural-320x256")
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    rng = np.random.default_rng(0)
    bundle = OnnxBundle(args.bundle, threads=args.threads)
    threshold = bundle.policy.support_threshold
    model = SCNeRF(bundle.cfg)
    model.renderer.load_state_dict(renderer_state_from_current_graph(args.bundle / "renderer.onnx", model))
    base, student = model.renderer, copy.deepcopy(model.renderer)
    examples = procedural_examples(bundle, args.scenes, args.targets, args.cache, rng)
    training = train(student, examples, args.samples, threshold, args.minutes, args.lr, rng)
    rows = []
    for name in SCENES:
        view = real_view(bundle, name, args.pixels)
        for label, renderer in (("default", base), ("trained for few samples", student)):
            rows.append({"view": name, "renderer": label, **score(renderer, view, args.samples, threshold)})
            print(f"{name} K={args.samples} {label}: {rows[-1]}", flush=True)
    results = {
        "args": {k: str(v) for k, v in vars(args).items()},
        "training": training,
        "rows": rows,
        "load": os.getloadavg(),
    }
    print(f"wrote {write_results(results, Path(__file__).parent / 'results', 'few-samples')}")


if __name__ == "__main__":
    main()
