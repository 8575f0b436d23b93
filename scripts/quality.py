#!/usr/bin/env python3
"""The quality table of docs/results.md: bundles side by side on the real validation scenes,
rendered through the real server (its scene API), scored the paper's way.

For every bundle, a fresh server; lego's val views and DTU scan37's test views (targets at half
size unless told otherwise), with per-target nearest sources (the paper's protocol) and with each
scene's fixed triple. Writes one
`scnerf-export eval` JSON per bundle, scene and protocol into OUT and prints the markdown table.

    .venv/bin/python scripts/quality.py --out results/quality \\
        default=bundles/default mvsnerf=bundles/mvsnerf-public procedural=bundles/procedural-only

A column may be one bundle with another sampling than the server's default (``--sampling
NAME=full|guided``): ``full=bundles/default guided=bundles/default --sampling full=full
--sampling guided=guided`` puts the two side by side; ``--band NAME=network`` likewise gives a
column the server's ``--band network`` (the network's own colour where a source misses the surface).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from scnerf_export.evaluate.eval import evaluate, write_json
from scnerf_export.serving import ServerProcess, find_server_binary

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"
# folder, format, the scale its images are read at, and whether it names fixed sources.
SCENES = {
    "lego": ("nerf_synthetic_lego", "blender", 1.0, True),
    "scan37": ("dtu_scan37", "dtu", 1.0, True),
    # LLFF's 504x378 set (images_8), every 8th view held out.
    "horns": ("llff_horns", "llff", 1 / 8, False),
}
PROTOCOLS = {"nearest": None, "fixed": ["fixed"]}


def measure(
    name: str,
    bundle: str,
    out: Path,
    scales: dict,
    target_scales: dict,
    views: dict,
    protocols: list[str],
    threads: int | None,
    sampling: str | None,
    band: str | None,
    scenes: list[str],
) -> None:
    binary = find_server_binary()
    if binary is None:
        sys.exit("no target/release/scnerf-server: cargo build --release -p scnerf-server")
    # Paper-size views take minutes on a few cores: a deadline far beyond the default 900 s.
    extra = (
        "--request-timeout-secs",
        "7200",
        *(("--sampling", sampling) if sampling else ()),
        *(("--band", band) if band else ()),
    )
    with ServerProcess(binary, bundle, threads=threads, extra=extra) as server:
        for scene in scenes:
            folder, fmt, scale, _ = SCENES[scene]
            for protocol in scene_protocols(scene, protocols):
                sources = PROTOCOLS[protocol]
                path = out / f"{name}-{scene}-{protocol}.json"
                if path.is_file():
                    continue
                print(f"{name}: {scene}, {protocol} sources", flush=True)
                summary = evaluate(
                    None,
                    SHARED / folder,
                    fmt,
                    sources=sources,
                    targets=views.get(scene),
                    scale=scales.get(scene, scale),
                    target_scale=target_scales.get(scene, 0.5),
                    server=server.url,
                )
                write_json(summary, path)


def scene_protocols(scene: str, protocols: list[str]) -> list[str]:
    """The protocols asked for that the scene has: "fixed" needs the scene's own fixed sources."""
    return [p for p in protocols if p != "fixed" or SCENES[scene][3]]


def table(names: list[str], out: Path, protocols: list[str], scenes: list[str]) -> str:
    lines = ["| scene, sources | view | " + " | ".join(names) + " |", "|---|---|" + "---|" * len(names)]
    for scene in scenes:
        for protocol in scene_protocols(scene, protocols):
            runs = [json.loads((out / f"{n}-{scene}-{protocol}.json").read_text()) for n in names]
            for view in [*runs[0]["views"], "mean"]:
                cells = []
                for run in runs:
                    row = run["mean"] if view == "mean" else run["views"][view]
                    cell = f"{row['psnr']:.2f} / {row['ssim']:.3f}"
                    if "psnr_masked" in row:
                        cell += f" (masked {row['psnr_masked']:.2f} / {row['ssim_masked']:.3f})"
                    cells.append(cell)
                label = f"**{view}**" if view == "mean" else view
                lines.append(f"| {scene}, {protocol} | {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def per_scene(items: list[str], convert) -> dict:
    """``["lego=0.25", ...]`` -> ``{"lego": convert("0.25"), ...}``."""
    return {scene: convert(value) for scene, _, value in (item.partition("=") for item in items)}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("bundles", nargs="+", help="NAME=DIR")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument(
        "--scale", action="append", default=[], metavar="SCENE=S", help="scale of a scene's images (default 1)"
    )
    p.add_argument(
        "--target-scale",
        action="append",
        default=[],
        metavar="SCENE=S",
        help="scale of a scene's targets, on top of --scale (default 0.5)",
    )
    p.add_argument("--views", action="append", default=[], metavar="SCENE=V,V", help="only these targets of a scene")
    p.add_argument("--protocols", type=lambda t: t.split(","), default=list(PROTOCOLS), help="nearest,fixed")
    p.add_argument(
        "--scenes", type=lambda t: t.split(","), default=list(SCENES), help="lego,scan37,horns (a refined bundle: its)"
    )
    p.add_argument("--threads", type=int)
    p.add_argument(
        "--sampling", action="append", default=[], metavar="NAME=MODE", help="a column's sampling (full or guided)"
    )
    p.add_argument(
        "--band", action="append", default=[], metavar="NAME=FILL", help="a column's --band (sources or network)"
    )
    args = p.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    pairs = [item.partition("=")[::2] for item in args.bundles]
    views = per_scene(args.views, lambda names: names.split(","))
    scales = per_scene(args.scale, float)
    target_scales = per_scene(args.target_scale, float)
    samplings, bands = per_scene(args.sampling, str), per_scene(args.band, str)
    for name, bundle in pairs:
        sampling, band = samplings.get(name), bands.get(name)
        protocols, scenes = args.protocols, args.scenes
        measure(name, bundle, args.out, scales, target_scales, views, protocols, args.threads, sampling, band, scenes)
    print(table([name for name, _ in pairs], args.out, args.protocols, args.scenes))
    return 0


if __name__ == "__main__":
    sys.exit(main())
