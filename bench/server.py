"""The Rust server end to end over HTTP: a cold request, then a scene encoded once and a view of it."""

from __future__ import annotations

import base64
import io
import json
import re
import time
from pathlib import Path

import numpy as np
from PIL import Image

from scnerf_export.serving import ServerProcess, multipart

from .report import psnr


def decode_json_rgb(body: bytes):
    doc = json.loads(body)
    rgb = np.asarray(Image.open(io.BytesIO(base64.b64decode(doc["rgb"]["data"]))).convert("RGB"), np.float32) / 255.0
    return doc, rgb


ACCEPT_JSON = {"Accept": "application/json"}


def multipart_request(document: dict, sources: list[bytes]) -> tuple[bytes, dict]:
    """A multipart body as curl sends it (the request JSON, then the source PNGs) and its headers."""
    body, ctype = multipart(
        [("request", "", json.dumps(document).encode(), "application/json")]
        + [(f"source_{i}", f"source_{i}.png", s, "image/png") for i, s in enumerate(sources)]
    )
    return body, {**ACCEPT_JSON, "Content-Type": ctype}


def timed_request(server: ServerProcess, path: str, body: bytes, headers: dict) -> tuple[int, bytes, dict, float]:
    """Status, body, headers and the client's wall time in ms of one POST."""
    start = time.perf_counter()
    status, data, answer_headers = server.request("POST", path, body, headers)
    return status, data, answer_headers, (time.perf_counter() - start) * 1000.0


def bench_server(args, bundle: str, scene_dir: Path, cached: bool = True) -> dict:
    """Fresh server per size (peak RSS per size): one cold /v1/render, then POST /v1/scenes and a
    /v1/scenes/{id}/render of the same target (cached scene)."""
    request = json.loads((scene_dir / "request.json").read_text())
    sources = [(scene_dir / f"source_{i}.png").read_bytes() for i in range(len(request["sources"]))]
    server = ServerProcess(Path(args.server_bin), bundle, args.threads, tuple(args.server_args))
    out: dict = {
        "method": "server",
        "startup_ms": server.startup_ms,
        "model_id": server.model.get("model_id"),
        "threads": args.threads,
    }
    try:
        out.update(cold_views(server, request, sources, args.repeats))
        out["peak_rss_mib_cold"] = server.peak_rss_mib()
        if cached:
            out.update(cached_views(server, request, sources, args.repeats, out["rgb"]))
        else:
            out["cached"] = "not measured at this size (--cached-sizes)"
        out["peak_rss_mib"] = server.peak_rss_mib()
    finally:
        server.stop()
    return out


def cold_views(server: ServerProcess, request: dict, sources: list[bytes], repeats: int) -> dict:
    """``repeats`` one-shot renders; the fastest's timings and image."""
    colds = []
    for _ in range(repeats):
        status, data, _, wall = timed_request(server, "/v1/render", *multipart_request(request, sources))
        if status != 200:
            raise RuntimeError(f"/v1/render answered {status}: {data[:500]!r}")
        doc, rgb = decode_json_rgb(data)
        colds.append({**doc["timings_ms"], "client_wall": wall})
    return {"cold_ms": min(colds, key=lambda t: t["client_wall"]), "cold_runs_ms": colds, "rgb": rgb}


def cached_views(server: ServerProcess, request: dict, sources: list[bytes], repeats: int, cold_rgb) -> dict:
    """The scene encoded once, then ``repeats`` renders of the target from it; the fastest's timings."""
    scene = {k: request[k] for k in ("sources", "near", "far", "background")}
    status, data, headers, create_wall = timed_request(server, "/v1/scenes", *multipart_request(scene, sources))
    if status in (404, 405):
        return {"cached": f"not available (POST /v1/scenes answered {status})"}
    if status not in (200, 201):
        return {"cached": f"failed (POST /v1/scenes answered {status}: {data[:300]!r})"}
    scene_id = json.loads(data)["scene_id"]
    out: dict = {"scene_create_ms": {**parse_server_timing(headers), "client_wall": create_wall}}
    view = json.dumps({"target": request["target"], "outputs": request["outputs"]}).encode()
    runs = []
    for _ in range(max(1, repeats)):
        status, data, _, wall = timed_request(
            server, f"/v1/scenes/{scene_id}/render", view, {**ACCEPT_JSON, "Content-Type": "application/json"}
        )
        if status != 200:
            out["cached"] = f"failed (render answered {status}: {data[:300]!r})"
            break
        doc, rgb = decode_json_rgb(data)
        runs.append({**doc["timings_ms"], "client_wall": wall})
    if runs:
        out["cached_ms"] = min(runs, key=lambda t: t["client_wall"])
        out["cached_matches_cold_psnr"] = psnr(rgb, cold_rgb)
    return out


def parse_server_timing(headers: dict) -> dict:
    value = next((v for k, v in headers.items() if k.lower() == "server-timing"), "")
    result = {}
    for item in value.split(","):
        m = re.match(r"\s*([\w-]+)\s*;\s*dur=([\d.]+)", item)
        if m:
            result[m.group(1)] = float(m.group(2))
    return result
