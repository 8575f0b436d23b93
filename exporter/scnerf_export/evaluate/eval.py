"""`scnerf-export eval`: render target views of a real scene through ONNX Runtime (or a running
server) and score them."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
from PIL import Image

from ..data import datasets
from ..runtime.onnx_pipeline import OnnxBundle
from ..serving import ServedBundle
from . import metrics


def split_names(value: str | None) -> list[str] | None:
    return [v.strip() for v in value.split(",") if v.strip()] if value else None


def evaluate(
    bundle_dir: str | Path,
    scene_dir: str | Path,
    fmt: str,
    sources: list[str] | None = None,
    targets: list[str] | None = None,
    scale: float = 1.0,
    near: float | None = None,
    far: float | None = None,
    threads: int | None = None,
    chunk: int | None = None,
    save_dir: str | Path | None = None,
    target_scale: float = 1.0,
    server: str | None = None,
    band: str = "sources",
) -> dict:
    """Render every target, through ONNX Runtime in this process or through the server at ``server``
    (its scene API, PNG output), and score it. Sources: ``sources`` for every target (``["fixed"]``: the
    scene's own fixed triple, MVSNeRF's r_6/r_43/r_33 or 25/21/33), or by default the paper's
    protocol: per target, the 3 views of the source pool (:func:`source_pool`) nearest to it by
    camera-centre distance. Each source triple is encoded once. ``band``: the colour of the pixels
    whose surface a source does not see, in this process (runtime/band.py); a server uses its own."""
    scene = datasets.load_scene(scene_dir, fmt, scale=scale, near=near, far=far)
    targets = targets or scene.default_targets
    if not targets:
        raise ValueError("this scene names no target views: pass --targets")
    if sources == ["fixed"]:
        sources = scene.default_sources
        if not sources:
            raise ValueError("this scene names no fixed source views: pass --sources A,B,C")
    pool = source_pool(scene, targets)
    bundle = ServedBundle(server) if server else OnnxBundle(bundle_dir, threads=threads)
    encoded: dict[tuple[str, ...], tuple[dict, float]] = {}
    rows = []
    for view in datasets.get_views(scene, targets):
        names = tuple(sources or datasets.nearest_sources(scene, view.name, pool))
        if names not in encoded:
            encoded[names] = encode_sources(bundle, scene, names)
        scene_tensors, encode_seconds = encoded[names]
        if target_scale != 1.0:
            view = downscale_target(view, target_scale)
        start = time.perf_counter()
        in_process = {} if server else {"band": band}
        result = bundle.render_target(
            scene_tensors, view.camera, scene.near, scene.far, scene.background, chunk, **in_process
        )
        seconds = time.perf_counter() - start
        row = {
            "view": view.name,
            "sources": list(names),
            "psnr": metrics.psnr(result.rgb, view.image),
            "ssim": metrics.ssim(result.rgb, view.image),
            "seconds": seconds,
            "seconds_with_encoding": seconds + encode_seconds,
        }
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
    summary = {
        "bundle": server or str(bundle_dir),
        "model_id": bundle.model_id,
        "scene": str(scene_dir),
        "protocol": PROTOCOL_FIXED if sources else PROTOCOL_NEAREST,
        "encode_seconds": sum(seconds for _, seconds in encoded.values()),
        "threads": threads,
        "format": fmt,
        "scale": scale,
        "target_scale": target_scale,
        "targets": targets,
        "near": scene.near,
        "far": scene.far,
        "views": {r["view"]: r for r in rows},
        "mean": metrics.mean_metrics(rows),
    }
    lpips_ok, reason = metrics.lpips_available("vgg")
    summary["lpips"] = None if not lpips_ok else "not computed"
    if not lpips_ok:
        summary["lpips_unavailable"] = reason
    print(format_row({"view": "mean", "sources": [], **summary["mean"]}), flush=True)
    return summary


def source_pool(scene: datasets.SceneData, targets: list[str]) -> list[str]:
    """Every view that is neither asked for nor one of the scene's own targets: targets are never sources."""
    excluded = set(targets) | set(scene.default_targets or [])
    return [name for name in scene.views if name not in excluded]


PROTOCOL_NEAREST = "per target, the 3 source-pool views nearest by camera-centre distance"
PROTOCOL_FIXED = "the same source views for every target"


def encode_sources(bundle: OnnxBundle, scene: datasets.SceneData, names: tuple[str, ...]) -> tuple[dict, float]:
    """The encoder and volume of one source triple (reference first), and the seconds it took."""
    views = datasets.get_views(scene, list(names))
    start = time.perf_counter()
    encoded = bundle.encode_scene(
        np.stack([v.image for v in views]), [v.camera for v in views], scene.near, scene.far, scene.background
    )
    seconds = time.perf_counter() - start
    print(f"sources {','.join(names)}: encoder + volume {seconds:.1f} s", flush=True)
    return encoded, seconds


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
    parts = [
        f"{row['view']:>8}",
        f"{','.join(row['sources']):>12}",
        f"PSNR {row['psnr']:6.2f}",
        f"SSIM {row['ssim']:.3f}",
    ]
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
