"""`python -m bench.sampling`: full against guided sampling through the server, on real scenes.

Per scene (Blender lego r_28, DTU scan37 view 32 and LLFF horns' first held-out view from
``../shared/data``, each with its 3 nearest source views, the paper's protocol) the sources are
encoded once as a scene; then per target size the view is rendered with ``"sampling": "full"``
and ``"guided"`` in turn (``--rounds`` rounds, the fastest of each kept), and each mode's
renderer time (the server's own stage timing), network samples per pixel and PSNR against the
ground truth are recorded. A size of another aspect than the scene's photos is the target camera
scaled to cover the size and cropped about its centre (square pixels; the ground truth scaled and
cropped alike). Writes ``bench/results/sampling-<date>.json`` and prints the markdown table of
docs/results.md.

    .venv/bin/python -m bench.sampling --bundle bundles/default --threads 2
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import time
from pathlib import Path

import numpy as np
from PIL import Image

from scnerf_export.cameras import Camera, camera_json
from scnerf_export.data import datasets
from scnerf_export.evaluate import metrics
from scnerf_export.evaluate.eval import source_pool
from scnerf_export.serving import ServerProcess, find_server_binary

from .scene import parse_sizes

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
# folder, format, the scale its images are read at, target view.
SCENES = {
    "lego": ("nerf_synthetic_lego", "blender", 1.0, "r_28"),
    "scan37": ("dtu_scan37", "dtu", 1.0, "32"),
    # LLFF's 504x378 set; its first held-out view (LLFF holds out every 8th).
    "horns": ("llff_horns", "llff", 1 / 8, "DJI_20200223_163016_842"),
}
MODES = ("full", "guided")


def cropped_target(camera: Camera, image: np.ndarray, width: int, height: int) -> tuple[Camera, np.ndarray]:
    """The camera and ground truth scaled to cover ``width`` x ``height`` (the larger of the two
    ratios) and cropped about the centre to it."""
    scale = max(width / camera.width, height / camera.height)
    scaled_width, scaled_height = max(width, round(camera.width * scale)), max(height, round(camera.height * scale))
    resized = camera.resized(scaled_width, scaled_height)
    left, top = (scaled_width - width) // 2, (scaled_height - height) // 2
    K = resized.K.copy()
    K[0, 2] -= left
    K[1, 2] -= top
    truth = np.asarray(
        Image.fromarray((image * 255).round().astype(np.uint8)).resize((scaled_width, scaled_height), Image.BOX),
        np.float32,
    )
    return Camera(K, resized.w2c, width, height), truth[top : top + height, left : left + width] / 255.0


def scene_upload(client, scene: datasets.SceneData, target: str) -> tuple[object, list[str]]:
    """The target's 3 nearest source views, uploaded once as a scene."""
    names = datasets.nearest_sources(scene, target, source_pool(scene, scene.default_targets))
    views = datasets.get_views(scene, names)
    images = [(v.image * 255).round().astype(np.uint8) for v in views]
    uploaded = client.upload_scene(
        images, [camera_json(v.camera) for v in views], near=scene.near, far=scene.far, background=scene.background
    )
    return uploaded, names


def encoded_target(bundle, name: str, width: int, height: int) -> tuple[datasets.SceneData, dict, Camera]:
    """Scene ``name`` of ``SCENES``, its target's 3 nearest sources encoded by ``bundle`` (an
    ``OnnxBundle``) and the target camera scaled and cropped to ``width`` x ``height``."""
    folder, fmt, scale, target = SCENES[name]
    scene = datasets.load_scene(SHARED / folder, fmt, scale=scale)
    names = datasets.nearest_sources(scene, target, source_pool(scene, scene.default_targets))
    views = datasets.get_views(scene, names)
    images = np.stack([v.image for v in views]).astype(np.float32)
    encoded = bundle.encode_scene(images, [v.camera for v in views], scene.near, scene.far, scene.background)
    view = datasets.get_views(scene, [target])[0]
    camera, _ = cropped_target(view.camera, view.image, width, height)
    return scene, encoded, camera


def measure(client, uploaded, camera: Camera, truth: np.ndarray, mask, rounds: int) -> dict:
    """Each mode's fastest renderer time over ``rounds`` interleaved rounds, its samples per pixel
    and PSNR (full image, and object-masked where the scene has masks)."""
    best: dict[str, dict] = {}
    for _ in range(rounds):
        for mode in MODES:
            start = time.perf_counter()
            r = client.render_scene(uploaded, camera_json(camera), outputs=["rgb"], sampling=mode)
            wall = (time.perf_counter() - start) * 1000.0
            row = {
                "renderer_ms": r.timings["renderer"],
                "total_ms": r.timings["total"],
                "client_ms": wall,
                "samples_per_ray": r.samples_per_ray,
                "psnr": metrics.psnr(r.rgb, truth),
            }
            if mask is not None:
                row["psnr_masked"] = metrics.dtu_masked_metrics(r.rgb, truth, mask)["psnr"]
            if mode not in best or row["renderer_ms"] < best[mode]["renderer_ms"]:
                best[mode] = row
    best["renderer_ratio"] = best["guided"]["renderer_ms"] / best["full"]["renderer_ms"]
    best["psnr_change"] = best["guided"]["psnr"] - best["full"]["psnr"]
    return best


def run(args) -> dict:
    binary = Path(args.server_bin) if args.server_bin else find_server_binary()
    if binary is None:
        raise SystemExit("no scnerf-server binary: cargo build --release -p scnerf-server")
    extra = ("--request-timeout-secs", "7200")
    results = {
        "bundle": args.bundle,
        "threads": args.threads,
        "rounds": args.rounds,
        "machine": os.uname().nodename,
        "cpu": cpu_name(),
        "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "load_before": os.getloadavg(),
        "protocol": "per target its 3 nearest source views; renderer time = the server's renderer stage",
        "scenes": {},
    }
    with ServerProcess(binary, args.bundle, threads=args.threads, extra=extra) as server:
        results["model_id"] = server.client.model()["model_id"]
        for name in args.scenes:
            folder, fmt, scale, target = SCENES[name]
            scene = datasets.load_scene(SHARED / folder, fmt, scale=scale)
            uploaded, sources = scene_upload(server.client, scene, target)
            view = datasets.get_views(scene, [target])[0]
            rows = {}
            for width, height in args.sizes:
                camera, truth = cropped_target(view.camera, view.image, width, height)
                mask = None if view.mask is None else cropped_mask(view, width, height)
                rows[f"{width}x{height}"] = measure(server.client, uploaded, camera, truth, mask, args.rounds)
                print(name, f"{width}x{height}", json.dumps(rows[f"{width}x{height}"], default=float), flush=True)
            results["scenes"][name] = {"target": target, "sources": sources, "sizes": rows}
    results["load_after"] = os.getloadavg()
    return results


def cropped_mask(view, width: int, height: int) -> np.ndarray:
    as_image = view.mask[..., None].repeat(3, -1).astype(np.float32)
    _, cropped = cropped_target(view.camera, as_image, width, height)
    return cropped[..., 0] > 0.5


def cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return "unknown"


def masked_psnr(row: dict) -> str:
    return f" ({row['psnr_masked']:.2f})" if "psnr_masked" in row else ""


def table(results: dict) -> str:
    """The markdown table of docs/results.md."""
    columns = [
        "scene", "size", "full: renderer s", "full: PSNR", "guided: renderer s", "guided: samples/px",
        "guided: PSNR", "renderer time", "PSNR change",
    ]  # fmt: skip
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    for name, scene in results["scenes"].items():
        for size, row in scene["sizes"].items():
            full, guided = row["full"], row["guided"]
            cells = [
                f"{name} {scene['target']}", size,
                f"{full['renderer_ms'] / 1e3:.1f}", f"{full['psnr']:.2f}{masked_psnr(full)}",
                f"{guided['renderer_ms'] / 1e3:.2f}", f"{guided['samples_per_ray']:.1f}",
                f"{guided['psnr']:.2f}{masked_psnr(guided)}",
                f"1/{1 / row['renderer_ratio']:.1f}", f"{row['psnr_change']:+.2f}",
            ]  # fmt: skip
            lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--bundle", default="bundles/default")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--rounds", type=int, default=1)
    p.add_argument("--sizes", type=parse_sizes, default=parse_sizes("160x128,320x256,640x512"))
    p.add_argument("--scenes", type=lambda s: s.split(","), default=list(SCENES))
    p.add_argument("--server-bin", help="the server binary (default: target/release/scnerf-server)")
    p.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    args = p.parse_args()
    results = run(args)
    print(f"wrote {write_results(results, args.out, 'sampling')}\n")
    print(table(results))


def write_results(results: dict, folder: Path, prefix: str) -> Path:
    """``results`` as ``folder/<prefix>-<date>.json``."""
    stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M")
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{prefix}-{stamp}.json"
    path.write_text(json.dumps(results, indent=2, default=float) + "\n")
    return path


if __name__ == "__main__":
    main()
