"""The volume build's time, before and after: ``python -m bench.volume_ab``.

Two servers, each a binary with a bundle (``--a BINARY:BUNDLE``, ``--b BINARY:BUNDLE``), run side
by side; each round posts the same scene (``POST /v1/scenes``: decode, encoder, volume; no view is
rendered) to A, B, B and A, and reads the server's own ``volume`` stage time from its
``Server-Timing`` header, then deletes the scene. Interleaved rounds put the machine's drift on
both alike (a shared 2-core machine drifts by tens of percent within minutes). Sizes as
``bench.memory``: 640x512 is DTU scan37 (views 33, 31, 25), 800x800 the Blender lego (r_6, r_43,
r_33), both at their own size.

    .venv/bin/python -m bench.volume_ab --a /tmp/base/scnerf-server:/tmp/base/bundles/default \\
        --b target/release/scnerf-server:bundles/default --sizes 640x512,800x800 --rounds 4 \\
        --out bench/results/volume-ab.json
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

from scnerf_export.cameras import camera_json
from scnerf_export.data.datasets import get_views, load_scene
from scnerf_export.data.scene import resize_view
from scnerf_export.serving import ServerProcess, png_bytes

from .memory import SHARED, triple_for
from .runner import machine


def scene_request(size: tuple[int, int]) -> dict:
    """The arguments of ``Client.upload_scene`` for the size's triple of sources."""
    triple = triple_for(size)
    scene = load_scene(SHARED / triple.scene, triple.format)
    views = [resize_view(v, *size) for v in get_views(scene, list(triple.sources))]
    return {
        "images": [png_bytes(v.image) for v in views],
        "cameras": [camera_json(v.camera) for v in views],
        "near": scene.near,
        "far": scene.far,
        "background": list(scene.background),
    }


def volume_ms(server: ServerProcess, request: dict) -> float:
    """The server's volume stage time of one scene upload (the scene is deleted afterwards)."""
    scene = server.client.upload_scene(**request)
    server.client.delete_scene(scene)
    return scene.timings["volume"]


def spread(values: list[float]) -> dict:
    return {"median": statistics.median(values), "min": min(values), "max": max(values), "all": values}


def measure(a: ServerProcess, b: ServerProcess, size: tuple[int, int], rounds: int) -> dict:
    request = scene_request(size)
    volume_ms(a, request), volume_ms(b, request)  # warm-up: sessions, first allocations
    times: dict[str, list[float]] = {"a": [], "b": []}
    for _ in range(rounds):
        for name, server in (("a", a), ("b", b), ("b", b), ("a", a)):
            times[name].append(volume_ms(server, request))
    # Each round's own ratio: B's two runs over A's two, taken together.
    ratios = [sum(times["b"][2 * i : 2 * i + 2]) / sum(times["a"][2 * i : 2 * i + 2]) for i in range(rounds)]
    return {
        "size": f"{size[0]}x{size[1]}",
        "a_ms": spread(times["a"]),
        "b_ms": spread(times["b"]),
        "ratio": spread(ratios),
    }


def server_spec(spec: str) -> tuple[Path, Path]:
    binary, _, bundle = spec.partition(":")
    return Path(binary), Path(bundle)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--a", required=True, type=server_spec, help="BINARY:BUNDLE, the before")
    p.add_argument("--b", required=True, type=server_spec, help="BINARY:BUNDLE, the after")
    p.add_argument("--sizes", default="640x512,800x800")
    p.add_argument("--rounds", type=int, default=4, help="rounds of A B B A per size")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--out", type=Path, help="write the figures as JSON here")
    args = p.parse_args()
    sizes = [tuple(int(x) for x in s.split("x")) for s in args.sizes.split(",")]
    extra = ("--request-timeout-secs", "3600")
    rows = []
    with ServerProcess(*args.a, threads=args.threads, extra=extra) as a:
        with ServerProcess(*args.b, threads=args.threads, extra=extra) as b:
            for size in sizes:
                row = measure(a, b, size, args.rounds)
                rows.append(row)
                print(
                    f"{row['size']}: volume A {row['a_ms']['median']:.0f} ms "
                    f"({row['a_ms']['min']:.0f}-{row['a_ms']['max']:.0f}), B {row['b_ms']['median']:.0f} ms "
                    f"({row['b_ms']['min']:.0f}-{row['b_ms']['max']:.0f}); B/A per round {row['ratio']['median']:.3f} "
                    f"({row['ratio']['min']:.3f}-{row['ratio']['max']:.3f})",
                    flush=True,
                )
    if args.out:
        result = {
            "a": [str(x) for x in args.a],
            "b": [str(x) for x in args.b],
            "threads": args.threads,
            "rounds": args.rounds,
            "when": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            # The ratio depends on the CPU's vector extensions (docs/results.md, "The volume build").
            "machine": machine(),
            "rows": rows,
        }
        args.out.write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
