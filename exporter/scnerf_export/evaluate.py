"""`scnerf-export eval`: render target views of a real scene through ONNX Runtime and score them."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
from PIL import Image

from . import datasets, metrics
from .onnx_pipeline import DEFAULT_CHUNK, OnnxBundle


def split_names(value: str | None) -> list[str] | None:
    return [v.strip() for v in value.split(",") if v.strip()] if value else None


def evaluate(bundle_dir: str | Path, scene_dir: str | Path, fmt: str, sources: list[str] | None = None,
             targets: list[str] | None = None, scale: float = 1.0, near: float | None = None,
             far: float | None = None, threads: int | None = None, chunk: int = DEFAULT_CHUNK,
             save_dir: str | Path | None = None, target_scale: float = 1.0) -> dict:
    scene = datasets.load_scene(scene_dir, fmt, scale=scale, near=near, far=far)
    sources = sources or scene.default_sources
    targets = targets or scene.default_targets
    if not sources or not targets:
        raise ValueError("this scene has no default source/target views: pass --sources and --targets")
    source_views = datasets.get_views(scene, sources)
    bundle = OnnxBundle(bundle_dir, threads=threads)
    images = np.stack([v.image for v in source_views])
    cameras = [v.camera for v in source_views]
    start = time.perf_counter()
    encoded = bundle.encode_scene(images, cameras, scene.near, scene.far, scene.background)
    encode_seconds = time.perf_counter() - start
    print(f"encoder + volume: {encode_seconds:.1f} s (once for all targets)", flush=True)
    rows = []
    for view in datasets.get_views(scene, targets):
        if target_scale != 1.0:
            view = downscale_target(view, target_scale)
        bundle.timings = {}
        start = time.perf_counter()
        result = bundle.render_target(encoded, view.camera, scene.near, scene.far, scene.background, chunk)
        seconds = time.perf_counter() - start
        row = {"view": view.name, "psnr": metrics.psnr(result.rgb, view.image), "ssim": metrics.ssim(result.rgb, view.image),
               "seconds": seconds, "seconds_with_encoding": seconds + encode_seconds}
        if view.mask is not None:
            masked = metrics.dtu_masked_metrics(result.rgb, view.image, view.mask)
            row.update({"psnr_masked": masked["psnr"], "ssim_masked": masked["ssim"]})
        if view.depth is not None:
            row["depth"] = metrics.depth_metrics(result.depth, view.depth)
        rows.append(row)
        if save_dir:
            out = Path(save_dir)
            out.mkdir(parents=True, exist_ok=True)
            Image.fromarray((np.clip(result.rgb, 0, 1) * 255).round().astype(np.uint8)).save(out / f"{view.name}.png")
        print(format_row(row), flush=True)
    summary = {"bundle": str(bundle_dir), "model_id": bundle.manifest["model_id"], "scene": str(scene_dir),
               "encode_seconds": encode_seconds, "threads": threads,
               "format": fmt, "scale": scale, "target_scale": target_scale, "sources": sources, "targets": targets,
               "near": scene.near, "far": scene.far, "views": {r["view"]: r for r in rows},
               "mean": metrics.mean_metrics(rows)}
    lpips_ok, reason = metrics.lpips_available("vgg")
    summary["lpips"] = None if not lpips_ok else "not computed"
    if not lpips_ok:
        summary["lpips_unavailable"] = reason
    print(format_row({"view": "mean", **summary["mean"]}), flush=True)
    return summary


def downscale_target(view: datasets.View, factor: float) -> datasets.View:
    """Render the target at 1/n of its size: the camera scaled (pixel centres kept at integers) and
    the ground truth box-averaged over n x n blocks, as the server's end-to-end test does."""
    n = round(1.0 / factor)
    if abs(n * factor - 1.0) > 1e-9 or view.image.shape[0] % n or view.image.shape[1] % n:
        raise ValueError(f"--target-scale must be 1/n with n dividing the image size, got {factor}")
    h, w = view.image.shape[0] // n, view.image.shape[1] // n
    image = view.image.reshape(h, n, w, n, 3).mean(axis=(1, 3)).astype(np.float32)
    mask = None if view.mask is None else view.mask.reshape(h, n, w, n).mean(axis=(1, 3)) > 0.5
    return datasets.View(view.name, image, view.camera.scaled(factor), depth=None, mask=mask)


def format_row(row: dict) -> str:
    parts = [f"{row['view']:>8}", f"PSNR {row['psnr']:6.2f}", f"SSIM {row['ssim']:.3f}"]
    if "psnr_masked" in row:
        parts += [f"masked PSNR {row['psnr_masked']:6.2f}", f"masked SSIM {row['ssim_masked']:.3f}"]
    if isinstance(row.get("depth"), dict) and "abs_err" in row["depth"]:
        parts.append(f"depth abs err {row['depth']['abs_err']:.4f}")
    if "seconds" in row:
        parts.append(f"{row['seconds']:.1f} s")
    return "  ".join(parts)


def write_json(summary: dict, path: str | Path) -> None:
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(json.dumps(summary, indent=2, default=float) + "\n")
