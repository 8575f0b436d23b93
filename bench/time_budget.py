"""`python -m bench.time_budget`: where a guided view's renderer time goes.

Per scene of ``bench.sampling`` (its target, 3 nearest sources, the target camera scaled and
cropped to ``--size``), one view by guided sampling through the ONNX Runtime twin
(``OnnxBundle.render_target``, the server's policy and graphs): network samples per pixel by stage
(level 0 at all S samples through ``renderer_guide.onnx``, each finer grid and the pixels rendered
again through ``renderer_fine.onnx``) and microseconds per network sample by graph. Then the FLOPs of
one sample (the matrix products of ``renderer.onnx``, ``bench.flops``, over its S samples), this
machine's fp32 GEMM rate (PyTorch's, ``--threads``, best of 5) and how far each graph runs from that
floor. Writes ``bench/results/time-budget-<date>.json`` and prints the table of docs/results.md.

    .venv/bin/python -m bench.time_budget --bundle bundles/default --threads 2 --size 640x512
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

from scnerf_export.export.manifest import Manifest
from scnerf_export.runtime.onnx_pipeline import OnnxBundle

from .flops import renderer_flops_for
from .sampling import SCENES, encoded_target, write_results
from .scene import parse_sizes

GRAPH_OF_STAGE = {"level 0": "renderer_guide"}  # every other stage runs renderer_fine


def gemm_gflops(threads: int, n: int = 2048, repeats: int = 5) -> float:
    """PyTorch's fp32 matrix-product rate with ``threads`` threads, the fastest of ``repeats``."""
    import torch

    torch.set_num_threads(threads)
    a, b = torch.randn(n, n), torch.randn(n, n)
    a @ b
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        a @ b
        best = min(best, time.perf_counter() - start)
    return 2.0 * n**3 / best / 1e9


def stage_rank(stage: str) -> tuple[int, int]:
    """Level 0, the grids coarse to fine, then the pixels rendered again (after any grid)."""
    if stage.startswith("grid "):
        return (1, -int(stage.split()[1]))
    return (0, 0) if stage == "level 0" else (2, 0)


def scene_view(bundle: OnnxBundle, name: str, width: int, height: int) -> dict:
    """One guided view of scene ``name``: samples per pixel by stage and seconds by graph."""
    scene, encoded, camera = encoded_target(bundle, name, width, height)
    bundle.graph_seconds = {}
    start = time.perf_counter()
    rendering = bundle.render_target(
        encoded, camera, scene.near, scene.far, scene.background, sampling="guided", band="network"
    )
    wall = time.perf_counter() - start
    pixels = width * height
    order = sorted(rendering.samples_by_stage, key=stage_rank)
    stages = {k: rendering.samples_by_stage[k] / pixels for k in order}
    samples_by_graph: dict[str, int] = {}
    for stage, samples in rendering.samples_by_stage.items():
        graph = GRAPH_OF_STAGE.get(stage, "renderer_fine")
        samples_by_graph[graph] = samples_by_graph.get(graph, 0) + samples
    return {
        "scene": f"{name} {SCENES[name][3]}",
        "size": f"{width}x{height}",
        "samples_per_pixel": rendering.samples_per_ray,
        "samples_per_pixel_by_stage": stages,
        "renderer_seconds": wall,
        "seconds_by_graph": dict(bundle.graph_seconds),
        "us_per_sample_by_graph": {
            g: 1e6 * bundle.graph_seconds[g] / n for g, n in samples_by_graph.items() if n and g in bundle.graph_seconds
        },
    }


def table(results: dict) -> str:
    floor_us = results["flops_per_sample"] / (results["gemm_gflops"] * 1e3)
    lines = [
        f"One sample: {results['flops_per_sample'] / 1e3:.0f} kFLOP of matrix products; PyTorch's fp32 GEMM "
        f"{results['gemm_gflops']:.0f} GFLOP/s at {results['threads']} threads: a floor of {floor_us:.2f} us a sample.",
        "",
        "| scene, size | samples per pixel: level 0, grids, rendered again (total) | renderer | "
        "us per sample: guide, fine (x the floor) |",
        "|---|---|---|---|",
    ]
    for row in results["views"]:
        st = row["samples_per_pixel_by_stage"]
        parts = ", ".join(f"{k} {v:.2f}" for k, v in st.items())
        us = row["us_per_sample_by_graph"]
        speed = ", ".join(
            f"{us[g]:.2f} ({us[g] / floor_us:.1f}x)" for g in ("renderer_guide", "renderer_fine") if g in us
        )
        lines.append(
            f"| {row['scene']}, {row['size']} | {parts} ({row['samples_per_pixel']:.2f}) | "
            f"{row['renderer_seconds']:.2f} s | {speed} |"
        )
    return "\n".join(lines)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--bundle", default="bundles/default")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--size", type=parse_sizes, default=parse_sizes("640x512"))
    p.add_argument("--scenes", type=lambda s: s.split(","), default=["scan37", "horns"])
    p.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    args = p.parse_args()
    bundle = OnnxBundle(args.bundle, threads=args.threads)
    cfg = Manifest.load(args.bundle).config
    ((width, height),) = args.size
    hw = (-(-height // cfg.image_multiple) * cfg.image_multiple, -(-width // cfg.image_multiple) * cfg.image_multiple)
    flops = renderer_flops_for(Path(args.bundle) / "renderer.onnx", 1024, hw, cfg.pad)
    results = {
        "threads": args.threads,
        "load_before": os.getloadavg(),
        "flops_per_sample": flops["per_ray"] / cfg.samples,
        "gemm_gflops": gemm_gflops(args.threads),
        "views": [scene_view(bundle, name, width, height) for name in args.scenes],
        "load_after": os.getloadavg(),
    }
    print(f"wrote {write_results(results, args.out, 'time-budget')}\n")
    print(table(results))


if __name__ == "__main__":
    main()
