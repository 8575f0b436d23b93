"""`scnerf-export experiment`: bundles side by side on held-out procedural scenes, per layout and
viewpoint gap (the paper's claim: rectification helps most far from the training distribution)."""

from __future__ import annotations

import json
from collections import defaultdict
from pathlib import Path

import numpy as np

from ..data.procedural import LAYOUTS, ProceduralDataset
from ..data.procedural.scenes import GAPS
from ..runtime.onnx_pipeline import OnnxBundle
from . import metrics


def depth_relative_error(depth: np.ndarray, truth: np.ndarray, alpha: np.ndarray) -> float:
    """Mean |D - D*| / D* over pixels whose ray hits an opaque surface (scale-free, so layouts
    with depth ranges of 2-5 and 2-300 units can be compared)."""
    valid = np.isfinite(truth) & (alpha >= 0.999) & (truth > 0)
    return float(np.mean(np.abs(depth[valid] - truth[valid]) / truth[valid]))


def procedural_rows(
    bundles: dict[str, Path],
    n_scenes: int = 9,
    width: int = 160,
    height: int = 128,
    cache_dir: Path | None = None,
    threads: int | None = None,
) -> list[dict]:
    data = ProceduralDataset("val", n_scenes=n_scenes, width=width, height=height, gaps=GAPS, cache_dir=cache_dir)
    examples = list(data.fixed_examples(targets_per_scene=1))
    rows = []
    for name, path in bundles.items():
        bundle = OnnxBundle(path, threads=threads)
        for ex in examples:
            images = np.stack([v.image for v in ex.sources])
            result = bundle.render_view(images, [v.camera for v in ex.sources], ex.target.camera, ex.near, ex.far)
            rows.append(
                {
                    "model": name,
                    "layout": ex.layout,
                    "gap": ex.gap,
                    "scene_seed": ex.scene_seed,
                    "psnr": metrics.psnr(result.rgb, ex.target.image),
                    "ssim": metrics.ssim(result.rgb, ex.target.image),
                    "depth_rel_err": depth_relative_error(result.depth, ex.target.depth, ex.target.alpha),
                }
            )
            print(json.dumps(rows[-1]), flush=True)
    return rows


def summarise(rows: list[dict]) -> dict[tuple[str, str, str], dict]:
    groups: dict[tuple[str, str, str], list[dict]] = defaultdict(list)
    for row in rows:
        groups[(row["model"], row["layout"], row["gap"])].append(row)
        groups[(row["model"], "all", row["gap"])].append(row)
    return {
        key: {
            **metrics.mean_metrics([{k: r[k] for k in ("psnr", "ssim", "depth_rel_err")} for r in group]),
            "n": len(group),
        }
        for key, group in groups.items()
    }


def markdown_table(summary: dict, models: list[str]) -> str:
    lines = [
        "| layout | gap | " + " | ".join(f"{m} PSNR / SSIM / depth rel. err" for m in models) + " |",
        "|---|---|" + "---|" * len(models),
    ]
    for layout in (*LAYOUTS, "all"):
        for gap in GAPS:
            cells = []
            for m in models:
                s = summary.get((m, layout, gap))
                cells.append("" if s is None else f"{s['psnr']:.2f} / {s['ssim']:.3f} / {s['depth_rel_err']:.3f}")
            lines.append(f"| {layout} | {gap} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def run(bundles: dict[str, Path], out_dir: Path, n_scenes: int, cache_dir: Path | None, threads: int | None) -> str:
    rows = procedural_rows(bundles, n_scenes=n_scenes, cache_dir=cache_dir, threads=threads)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "procedural.json").write_text(json.dumps(rows, indent=1) + "\n")
    table = markdown_table(summarise(rows), list(bundles))
    (out_dir / "procedural.md").write_text(table)
    return table
