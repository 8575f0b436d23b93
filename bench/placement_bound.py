"""`python -m bench.placement_bound`: what K samples a pixel can give when they are placed perfectly.

A sampler placed by the cost volume (a proposal network, a depth head) can at best know each ray's
own compositing weights before the renderer runs. This bench gives the fine renderer exactly that
oracle and measures what is left. Per scene of ``bench.sampling`` (its target, 3 nearest sources,
the target camera scaled and cropped to ``--size``): level 0 (every 8th pixel at all S samples)
for the rectifier heads, then ``--pixels`` random pixels rendered at all S samples (full sampling:
the reference and the oracle's weights), and again through ``renderer_fine.onnx``:

* at all S samples with the nearest level-0 ray's heads (what the heads alone change);
* at the K samples where the pixel's own full weights are highest, each standing for the nearby
  samples of its support (``select_samples`` on the pixel's own weights), for each ``--counts``.

Per row: the share of the pixel's weight on its K samples, the mean absolute error against full,
and the share of pixels more than 0.25 from full in a channel (the speckle bound is 0.1 %).

    .venv/bin/python -m bench.placement_bound --size 320x256 --counts 4,8,16
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import numpy as np

from scnerf_export import cameras as cams
from scnerf_export.runtime import guided
from scnerf_export.runtime.onnx_pipeline import OnnxBundle

from .sampling import SCENES, encoded_target, write_results
from .scene import parse_sizes

SPECKLE = 0.25


def errors(out: dict, full: np.ndarray, background: np.ndarray) -> dict:
    """Mean absolute error and the share of pixels beyond ``SPECKLE`` in a channel, against full."""
    composited = out["rgb"] + (1.0 - out["opacity"])[:, None] * background
    gap = np.abs(composited - full).max(axis=1)
    return {
        "mean_abs_error": float(np.abs(composited - full).mean()),
        "beyond_0_25_pct": float(100 * (gap > SPECKLE).mean()),
    }


def scene_bound(bundle: OnnxBundle, name: str, width: int, height: int, pixels: int, counts: list[int]) -> list[dict]:
    scene, encoded, camera = encoded_target(bundle, name, width, height)
    origins, directions = cams.target_rays(camera)
    background = np.asarray(scene.background, np.float32)
    guide, fine = bundle.guided_runs(encoded, scene.near, scene.far)
    rng = np.random.default_rng(0)
    rows = np.sort(rng.choice(width * height, min(pixels, width * height), replace=False))
    picked = np.stack([rows // width, rows % width], axis=1)
    full = guide(origins[rows], directions[rows])
    own = full["weights"]
    full_rgb = full["rgb"] + (1.0 - full["opacity"])[:, None] * background
    step = bundle.policy.step
    first = guided.first_level_pixels(width, height, step)
    guide(origins[first[:, 0] * width + first[:, 1]], directions[first[:, 0] * width + first[:, 1]])
    heads_of = guided.nearest_guide(picked, (width - 1) // step + 1, (height - 1) // step + 1, step)
    s = own.shape[1]
    every = np.broadcast_to(np.arange(s, dtype=np.float32), (len(rows), s)).copy()
    at = (origins[rows], directions[rows])
    label = f"{name} {SCENES[name][3]}, {width}x{height}"
    found = [{"view": label, "samples": s, "placed": "all, the guide's heads", "weight_on_samples": 1.0}]
    found[0] |= errors(fine(*at, every, np.ones_like(every), heads_of), full_rgb, background)
    for k in counts:
        index, multiplicity, _ = guided.select_samples(own, k, bundle.policy.support_threshold)
        on = np.take_along_axis(own, index, axis=1).sum(axis=1) / np.maximum(own.sum(axis=1), 1e-6)
        row = {"view": label, "samples": k, "placed": "the pixel's own heaviest", "weight_on_samples": float(on.mean())}
        found.append(row | errors(fine(*at, index.astype(np.float32), multiplicity, heads_of), full_rgb, background))
    return found


def table(rows: list[dict]) -> str:
    lines = [
        "| view | samples | placed at | weight on them | mean abs error | beyond 0.25 |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['view']} | {r['samples']} | {r['placed']} | {r['weight_on_samples']:.2f} | "
            f"{r['mean_abs_error']:.4f} | {r['beyond_0_25_pct']:.2f} % |"
        )
    return "\n".join(lines)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--bundle", default="bundles/default")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--size", type=parse_sizes, default=parse_sizes("320x256"))
    p.add_argument("--scenes", type=lambda s: s.split(","), default=list(SCENES))
    p.add_argument("--pixels", type=int, default=6000)
    p.add_argument("--counts", type=lambda s: [int(k) for k in s.split(",")], default=[4, 8, 16])
    p.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    args = p.parse_args()
    bundle = OnnxBundle(args.bundle, threads=args.threads)
    ((width, height),) = args.size
    rows = [r for name in args.scenes for r in scene_bound(bundle, name, width, height, args.pixels, args.counts)]
    print(f"wrote {write_results({'rows': rows, 'load': os.getloadavg()}, args.out, 'placement-bound')}\n")
    print(table(rows))


if __name__ == "__main__":
    main()
