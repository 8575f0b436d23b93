"""Where one renderer run's time goes, node by node, and whether the order of its rays matters.

ONNX Runtime's profiler on renderer runs of the benchmark scene (bench/scene.py, at any size): the
kernel time per op type and the slowest nodes with their shapes. Each ``--tiles`` entry is a ray
order: a run takes the pixels of an R x C tile (rows x columns; 1x512 is a piece of a row, as the
server cuts them) at every ``--at`` position; the orders take turns within each round, so a
drift of the machine's speed shifts all of them alike.

    .venv/bin/python -m bench.chunk_profile --size 640x512
    .venv/bin/python -m bench.chunk_profile --size 640x512 --tiles 1x512,16x32,32x16 \\
        --at 250,64 --at 200,100 --at 300,100 --at 260,40 --rounds 10
"""

from __future__ import annotations

import argparse
import collections
from pathlib import Path

import numpy as np
import onnxruntime as ort

from scnerf_export.runtime.onnx_pipeline import OnnxBundle, session_options

from . import REPO
from .profile import kernel_events_by_run
from .scene import make_scene_dir, parse_sizes, renderer_run_feeds

PRODUCTS = ("Gemm", "MatMul", "FusedGemm", "FusedMatMul")


def tile_pixels(rows: int, cols: int, top: int, left: int, width: int) -> np.ndarray:
    return np.array([(top + r) * width + left + c for r in range(rows) for c in range(cols)])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--bundle", default=str(REPO / "bundles/default"))
    parser.add_argument("--size", default="640x512", help="WxH of the benchmark scene")
    parser.add_argument("--tiles", default="1x512", help="ray orders, RxC tiles (comma-separated)")
    parser.add_argument(
        "--at",
        action="append",
        default=[],
        metavar="ROW,COL",
        help="top-left pixel of a run (repeatable; default: the tiles centred in the view)",
    )
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--nodes", type=int, default=12, help="slowest nodes listed (first order only)")
    parser.add_argument("--cache", default=str(REPO / "bench/.cache"))
    args = parser.parse_args()

    ((width, height),) = parse_sizes(args.size)
    tiles = [tuple(int(v) for v in t.split("x")) for t in args.tiles.split(",")]
    centred = ((height - max(r for r, _ in tiles)) // 2, (width - max(c for _, c in tiles)) // 2)
    spots = [tuple(int(v) for v in at.split(",")) for at in args.at] or [centred]
    if len({rows * cols for rows, cols in tiles}) > 1:
        parser.error("--tiles: every order must take the same number of rays per run")
    if any(top + rows > height or left + cols > width for rows, cols in tiles for top, left in spots):
        parser.error(f"a tile at an --at position leaves the {width}x{height} view")
    runs = [(t, tile_pixels(*t, top, left, width)) for t in tiles for top, left in spots]

    bundle = OnnxBundle(args.bundle, threads=args.threads)
    scene = make_scene_dir(Path(args.cache), width, height)
    everything = renderer_run_feeds(bundle, scene, np.concatenate([p for _, p in runs]))
    feeds, start = [], 0
    for _, pixels in runs:
        stop = start + len(pixels)
        feeds.append(
            {
                **everything,
                "ray_origins": everything["ray_origins"][start:stop],
                "ray_directions": everything["ray_directions"][start:stop],
            }
        )
        start = stop

    options = session_options(args.threads)
    options.enable_profiling = True
    options.profile_file_prefix = str(Path(args.cache) / "tmp" / "chunk-profile")
    Path(options.profile_file_prefix).parent.mkdir(parents=True, exist_ok=True)
    renderer = bundle.graph_path("renderer")
    session = ort.InferenceSession(str(renderer), options, providers=["CPUExecutionProvider"])
    for f in feeds:  # first runs allocate the arenas; not counted
        session.run(None, f)
    for _ in range(args.rounds):
        for f in feeds:
            session.run(None, f)
    measured = kernel_events_by_run(Path(session.end_profiling()))[len(feeds) :]

    by_tile: dict[tuple, list[collections.Counter]] = collections.defaultdict(list)
    for k, events in enumerate(measured):
        ops = collections.Counter()
        for e in events:
            ops[e["args"]["op_name"]] += e["dur"] / 1000.0
        by_tile[runs[k % len(runs)][0]].append(ops)
    print(f"{renderer} at {width}x{height}, {args.rounds} rounds x {len(spots)} positions; medians in ms")
    for tile, counters in by_tile.items():
        totals = [sum(c.values()) for c in counters]
        top = collections.Counter({op: float(np.median([c[op] for c in counters])) for op in counters[0]})
        products = np.median([sum(c[op] for op in PRODUCTS) for c in counters])
        print(
            f"{tile[0]}x{tile[1]}: kernels {np.median(totals):.1f} (fastest {min(totals):.1f}), "
            f"matrix products {products:.1f}; " + ", ".join(f"{op} {ms:.2f}" for op, ms in top.most_common(8))
        )

    first = [events for k, events in enumerate(measured) if runs[k % len(runs)][0] == tiles[0]]
    nodes: collections.Counter = collections.Counter()
    shapes = {}
    for events in first:
        for e in events:
            name = e["name"][: -len("_kernel_time")]
            nodes[(e["args"]["op_name"], name)] += e["dur"] / 1000.0 / len(first)
            shapes[name] = [list(t.values())[0] for t in e["args"].get("input_type_shape", [])][:2]
    print(f"slowest nodes ({tiles[0][0]}x{tiles[0][1]}, mean ms per run):")
    for (op, name), ms in nodes.most_common(args.nodes):
        print(f"  {ms:6.2f}  {op:12s} {name[:56]:56s} {shapes[name]}")


if __name__ == "__main__":
    main()
