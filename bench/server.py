"""The Rust server end to end over HTTP, through scnerf_client: a cold request, then a scene
encoded once and a view of it."""

from __future__ import annotations

import json
import time
from pathlib import Path

from scnerf_client import Client, Rendering, ServerError
from scnerf_export.serving import ServerProcess

from .report import psnr


def timed_render(call) -> tuple[Rendering, float]:
    """A rendering and the client's wall time in ms of the call that made it."""
    start = time.perf_counter()
    rendering = call()
    return rendering, (time.perf_counter() - start) * 1000.0


def bench_server(args, bundle: str, scene_dir: Path, cached: bool = True) -> dict:
    """Fresh server per size (peak RSS per size): one cold /v1/render, then PUT /v1/scenes/{id}
    and a /v1/scenes/{id}/render of the same target (cached scene)."""
    request = json.loads((scene_dir / "request.json").read_text())
    sources = [(scene_dir / f"source_{i}.png").read_bytes() for i in range(len(request["sources"]))]
    extra = (*args.server_args, "--sampling", args.sampling)
    server = ServerProcess(Path(args.server_bin), bundle, args.threads, extra)
    out: dict = {
        "method": "server",
        "startup_ms": server.startup_ms,
        "model_id": server.model.get("model_id"),
        "threads": args.threads,
    }
    try:
        out.update(cold_views(server.client, request, sources, args.repeats))
        out["peak_rss_mib_cold"] = server.peak_rss_mib()
        if cached:
            out.update(cached_views(server.client, request, sources, args.repeats, out["rgb"]))
        else:
            out["cached"] = "not measured at this size (--cached-sizes)"
        out["peak_rss_mib"] = server.peak_rss_mib()
    finally:
        server.stop()
    return out


def cold_views(client: Client, request: dict, sources: list[bytes], repeats: int) -> dict:
    """``repeats`` one-shot renders; the fastest's timings and image."""
    cameras = [s["camera"] for s in request["sources"]]
    colds = []
    for _ in range(repeats):
        rendering, wall = timed_render(
            lambda: client.render(
                sources,
                cameras,
                request["target"],
                request["near"],
                request["far"],
                request.get("background"),
                request["outputs"],
            )
        )
        colds.append({**rendering.timings, "client_wall": wall})
    return {"cold_ms": min(colds, key=lambda t: t["client_wall"]), "cold_runs_ms": colds, "rgb": rendering.rgb}


def cached_views(client: Client, request: dict, sources: list[bytes], repeats: int, cold_rgb) -> dict:
    """The scene encoded once, then ``repeats`` renders of the target from it; the fastest's timings."""
    cameras = [s["camera"] for s in request["sources"]]
    start = time.perf_counter()
    try:
        scene = client.upload_scene(sources, cameras, request["near"], request["far"], request.get("background"))
    except ServerError as e:
        return {"cached": f"failed (the scene upload answered {e.status}: {e.message[:300]})"}
    out: dict = {"scene_create_ms": {**scene.timings, "client_wall": (time.perf_counter() - start) * 1000.0}}
    runs = []
    for _ in range(max(1, repeats)):
        try:
            rendering, wall = timed_render(lambda: client.render_scene(scene, request["target"], request["outputs"]))
        except ServerError as e:
            out["cached"] = f"failed (render answered {e.status}: {e.message[:300]})"
            break
        runs.append({**rendering.timings, "client_wall": wall})
    if runs:
        out["cached_ms"] = min(runs, key=lambda t: t["client_wall"])
        out["cached_matches_cold_psnr"] = psnr(rendering.rgb, cold_rgb)
    return out
