"""Where a request's memory goes: ``python -m bench.memory``.

For each bundle and source size, a fresh server (release build, ``--memory-probe on``) renders
one view through ``POST /v1/render`` (multipart, by scnerf_client) from a real triple of source
views resized to that size. The probe resets the process's peak resident set (``VmHWM``) before
each stage (decoding the sources, each graph run) and reads it after, so each stage's peak is its
own; the table gives, per stage, that peak and the resident set after the stage's last run (what
it left held), the process at rest before the request and a few seconds after it. Sizes 320x256
and 640x512 are DTU scan37 (views 33, 31, 25 -> 32; 640x512 is its own size), 800x800 and
1024x1024 the Blender lego (r_6, r_43, r_33 -> r_28; 800x800 is its own size); the targets are
``--targets`` (each a row; default 80x64). ``--scene-views N`` adds, per source size, a row of
``POST /v1/scenes`` with N views (the triple's images in turn): a capture's upload, decoded and
kept, no volume built. ``--capture-views N`` adds, per square source size, a row of
``POST /v1/captures`` with a Blender capture of N views (lego's training photos in turn, resized),
read by the server's readers and decoded as a scene's.

A watchdog stops a server when the machine's available memory falls under ``--keep-free-mb``
(the machine is shared): that measurement is then reported as stopped, with the peak reached.
"""

from __future__ import annotations

import argparse
import json
import re
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from scnerf_client import Client, ConnectionFailed, ServerError
from scnerf_export.cameras import camera_json
from scnerf_export.data.datasets import get_views, load_scene
from scnerf_export.data.scene import resize_view
from scnerf_export.export.manifest import Manifest
from scnerf_export.runtime.volume_slabs import volume_build
from scnerf_export.serving import REPO, ServerProcess, find_server_binary, png_bytes

SHARED = REPO.parent / "shared" / "data"
SIZES = ("320x256", "640x512", "800x800", "1024x1024")
TARGETS = ("80x64",)


@dataclass(frozen=True)
class Triple:
    scene: str
    format: str
    sources: tuple[str, str, str]
    target: str


SCAN37 = Triple("dtu_scan37", "dtu", ("33", "31", "25"), "32")
LEGO = Triple("nerf_synthetic_lego", "blender", ("r_6", "r_43", "r_33"), "r_28")


def triple_for(size: tuple[int, int]) -> Triple:
    """scan37 for the 5:4 sizes, lego for the square ones."""
    return SCAN37 if size[0] != size[1] else LEGO


def request_for(triple: Triple, size: tuple[int, int], target: tuple[int, int] | None, views: int = 3) -> dict:
    """The arguments of ``Client.render`` for one render of ``triple`` with sources at ``size`` and
    a ``target`` view, or (``target`` None) of ``Client.upload_scene`` for a scene of ``views``
    views: the triple's in turn."""
    scene = load_scene(SHARED / triple.scene, triple.format)
    triple_views = get_views(scene, list(triple.sources))
    sources = []
    for view in triple_views:
        resized = resize_view(view, *size)
        sources.append((resized.camera, png_bytes(resized.image)))
    sources = [sources[i % len(sources)] for i in range(views)]
    request = {
        "images": [data for _, data in sources],
        "cameras": [camera_json(c) for c, _ in sources],
        "near": scene.near,
        "far": scene.far,
        "background": list(scene.background),
    }
    if target:
        request["target"] = camera_json(scene.views[triple.target].camera.resized(*target))
    return request


def capture_for(size: tuple[int, int], views: int, into: Path) -> dict:
    """A Blender capture folder of ``views`` views at ``size`` (square) in ``into``: lego's
    training photos in turn, resized; the arguments of ``Client.upload_capture`` for it."""
    from PIL import Image

    lego = SHARED / LEGO.scene
    transforms = json.loads((lego / "transforms_train.json").read_text())
    frames = [f for f in transforms["frames"] if (lego / f"{f['file_path']}.png").is_file()]
    (into / "train").mkdir(parents=True)
    chosen = []
    for i in range(views):
        frame = frames[i % len(frames)]
        with Image.open(lego / f"{frame['file_path']}.png") as photo:
            photo.resize(size, Image.LANCZOS).save(into / "train" / f"v_{i:03d}.png")
        chosen.append({**frame, "file_path": f"./train/v_{i:03d}"})
    (into / "transforms_train.json").write_text(json.dumps({**transforms, "frames": chosen}))
    return {"folder": into}


def request_status(client: Client, request: dict) -> tuple[int | None, str, float | None]:
    """Status of one render, scene upload or capture upload without retries (``client`` made
    with ``max_retries=0``): 200 or 201, the server's refusal (its message and Retry-After), or
    None when the server did not answer."""
    try:
        if "folder" in request:
            client.upload_capture(**request)
            return 201, "", None
        if "target" in request:
            client.render(**request, outputs=["rgb"])
            return 200, "", None
        client.upload_scene(**request)
        return 201, "", None
    except ServerError as e:
        return e.status, e.message, getattr(e, "retry_after", None)
    except ConnectionFailed as e:
        return None, str(e), None


def mib(value: float) -> float:
    return round(value / (1 << 20), 1)


def process_memory(pid: int) -> dict:
    status = Path(f"/proc/{pid}/status").read_text()
    field = {k: int(re.search(rf"{k}:\s+(\d+) kB", status).group(1)) * 1024 for k in ("VmRSS", "VmHWM")}
    return {"rss_mib": mib(field["VmRSS"]), "hwm_mib": mib(field["VmHWM"])}


def available_mib() -> float:
    text = Path("/proc/meminfo").read_text()
    return int(re.search(r"MemAvailable:\s+(\d+) kB", text).group(1)) / 1024.0


class Watchdog:
    """Terminates ``proc`` when the machine's available memory falls under ``keep_free_mib``."""

    def __init__(self, proc, keep_free_mib: float):
        self.proc, self.keep_free, self.fired, self.lowest = proc, keep_free_mib, False, float("inf")
        self.done = threading.Event()
        threading.Thread(target=self._watch, daemon=True).start()

    def _watch(self) -> None:
        while not self.done.wait(0.05):
            free = available_mib()
            self.lowest = min(self.lowest, free)
            if free < self.keep_free and self.proc.poll() is None:
                self.fired = True
                self.proc.kill()
                return


def stage_metrics(metrics: str) -> dict:
    """Per stage: peak and after, MiB, from the probe's gauges."""
    out: dict = {}
    for kind, key in (("stage_peak_resident_bytes", "peak_mib"), ("stage_resident_after_bytes", "after_mib")):
        for stage, value in re.findall(rf'scnerf_{kind}{{stage="(\w+)"}} (\d+)', metrics):
            out.setdefault(stage, {})[key] = mib(int(value))
    return out


def measure(
    binary: Path,
    bundle: Path,
    size: tuple[int, int],
    target: tuple[int, int] | None,
    views: int,
    args,
    capture: Path | None = None,
):
    """One request on a fresh server: a render of ``target`` from 3 sources at ``size``, or (no
    target) a scene upload of ``views`` views, or the capture folder ``capture`` of them."""
    request = capture_for(size, views, capture) if capture else request_for(triple_for(size), size, target, views)
    # A server without the probe (one built before it, for the "before" figures) gives only the
    # process's peak over the request (VmHWM: the warm-up's peak is cleared first where possible).
    extra = (*(("--memory-probe", "on") if args.probe else ()), *args.server_arg)
    server = ServerProcess(binary, bundle, args.threads, extra)
    dog = Watchdog(server.proc, args.keep_free_mb)
    out: dict = {
        "bundle": str(bundle),
        "model_id": server.model.get("model_id"),
        "sources": "x".join(map(str, size)),
        "views": views,
        "target": "x".join(map(str, target)) if target else None,
        "capture": capture is not None,
    }
    if capture:
        files = [f for f in capture.rglob("*") if f.is_file()]
        out["body_bytes"] = sum(f.stat().st_size for f in files)
        out["metadata_bytes"] = sum(f.stat().st_size for f in files if f.suffix == ".json")
    else:
        out["body_bytes"] = sum(map(len, request["images"])) + len(json.dumps(request["cameras"]))
    try:
        out["at_rest"] = process_memory(server.proc.pid)
        if not args.probe:
            # Clears the warm-up's peak (proc(5): "5" resets VmHWM to the resident set).
            Path(f"/proc/{server.proc.pid}/clear_refs").write_text("5")
        start = time.perf_counter()
        status, error, _ = request_status(Client(server.url, max_retries=0), request)
        out["seconds"] = round(time.perf_counter() - start, 1)
        out["status"] = status
        if status not in (200, 201):
            out["error"] = error[:300]
        if server.proc.poll() is None:
            out["stages"] = stage_metrics(server.client.metrics())
            time.sleep(args.settle_secs)
            out["after_request"] = process_memory(server.proc.pid)
    finally:
        dog.done.set()
        out["watchdog_stopped"] = dog.fired
        out["machine_available_mib_lowest"] = round(dog.lowest)
        server.stop()
    stages = out.get("stages", {})
    if args.probe and not target:
        # A scene's upload runs no graph: the graphs' figures are the warm-up's.
        out["request_peak_mib"] = stages.get("decode", {}).get("peak_mib")
    elif args.probe:
        out["request_peak_mib"] = max((s.get("peak_mib", 0.0) for s in stages.values()), default=None)
        before = [s.get("peak_mib", 0.0) for name, s in stages.items() if not name.startswith("renderer")]
        out["before_renderer_peak_mib"] = max(before, default=None)
    else:
        out["request_peak_mib"] = out.get("after_request", {}).get("hwm_mib")
    return out


def table(rows: list[dict]) -> str:
    stages = ["decode", "encoder", "volume", "cost_slab", "cost_conv", "volume_net", "renderer"]
    used = [s for s in stages if any(s in r.get("stages", {}) for r in rows)]
    head = ["bundle", "sources", "target", "at rest"] + [f"{s} peak / after" for s in used]
    head += ["request peak", "after request"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        target = r.get("target") or f"{'capture' if r.get('capture') else 'scene'} of {r.get('views', 3)}"
        cells = [Path(r["bundle"]).name, r["sources"], target, f"{r['at_rest']['rss_mib']:.0f}"]
        for s in used:
            m = r.get("stages", {}).get(s)
            cells.append(f"{m['peak_mib']:.0f} / {m['after_mib']:.0f}" if m else "-")
        peak = r.get("request_peak_mib")
        note = (
            ""
            if r.get("status") in (200, 201)
            else f" ({'stopped by the watchdog' if r['watchdog_stopped'] else r.get('status')})"
        )
        cells.append(f"{peak:.0f}{note}" if peak else f"-{note}")
        cells.append(f"{r['after_request']['rss_mib']:.0f}" if "after_request" in r else "-")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def update_fixture(path: Path, rows: list[dict]) -> None:
    """Merges the served rows into the server's fixture of measured peaks
    (tests/fixtures/memory/measured.json, read by pipeline::estimate's tests): per bundle (by model
    id and the way it builds its volume) its config, per source size, view count and target (0x0:
    a scene's upload) the peak above the process at rest."""
    fixture = json.loads(path.read_text()) if path.exists() else {"bundles": {}, "rows": []}

    def key(x: dict) -> tuple:
        return x["bundle"], x["build"], x["sources"], x.get("views", 3), x["target"], x.get("capture", False)

    for r in rows:
        if r.get("status") not in (200, 201) or not r.get("request_peak_mib"):
            continue
        manifest = Manifest.load(r["bundle"])
        build = volume_build(manifest.graphs)
        fixture["bundles"][r["model_id"]] = {"config": manifest.config.to_dict()}
        row = {
            "bundle": r["model_id"],
            "build": build,
            "sources": [int(v) for v in r["sources"].split("x")],
            "views": r.get("views", 3),
            "target": [int(v) for v in r["target"].split("x")] if r.get("target") else [0, 0],
            "peak_above_rest_mib": round(r["request_peak_mib"] - r["at_rest"]["rss_mib"], 1),
        }
        if "body_bytes" in r:
            row["body_bytes"] = r["body_bytes"]
        if r.get("capture"):
            row |= {"capture": True, "metadata_bytes": r["metadata_bytes"]}
        if before := r.get("before_renderer_peak_mib"):
            row["before_renderer_peak_above_rest_mib"] = round(before - r["at_rest"]["rss_mib"], 1)
        fixture["rows"] = [x for x in fixture["rows"] if key(x) != key(row)] + [row]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(fixture, indent=1) + "\n")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--bundle", action="append", required=True, help="bundle directory (repeatable)")
    parser.add_argument("--sizes", default=",".join(SIZES), help="source sizes WxH, comma-separated")
    parser.add_argument("--targets", default=",".join(TARGETS), help="target sizes WxH, comma-separated")
    parser.add_argument(
        "--scene-views", default="", help="view counts of scene uploads to measure per source size, comma-separated"
    )
    parser.add_argument(
        "--capture-views", default="", help="view counts of capture uploads per square source size, comma-separated"
    )
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--server-bin", default=None)
    parser.add_argument("--server-arg", action="append", default=[], help="extra server flag (repeatable)")
    parser.add_argument(
        "--no-probe", dest="probe", action="store_false", help="server without --memory-probe: process peak only"
    )
    parser.add_argument("--keep-free-mb", type=float, default=1536.0)
    parser.add_argument("--settle-secs", type=float, default=3.0)
    parser.add_argument("--out", default=None, help="JSON file for the results")
    parser.add_argument("--fixture", type=Path, default=None, help="merge the rows into this measured.json")
    args = parser.parse_args(argv)
    binary = find_server_binary(args.server_bin)

    def pairs(text: str) -> list[tuple[int, int]]:
        return [tuple(int(v) for v in s.split("x")) for s in text.split(",") if s]

    sizes, targets = pairs(args.sizes), pairs(args.targets)
    scene_views = [int(v) for v in args.scene_views.split(",") if v]
    runs = [(size, target, 3) for size in sizes for target in targets]
    runs += [(size, None, views) for size in sizes for views in scene_views]
    capture_views = [int(v) for v in args.capture_views.split(",") if v]
    captures = [(size, views) for size in sizes if size[0] == size[1] for views in capture_views]
    rows = []
    for bundle in args.bundle:
        for size, target, views in runs:
            rows.append(measure(binary, Path(bundle), size, target, views, args))
            print(json.dumps(rows[-1]), flush=True)
        for size, views in captures:
            with tempfile.TemporaryDirectory(prefix="capture-") as folder:
                rows.append(measure(binary, Path(bundle), size, None, views, args, capture=Path(folder)))
            print(json.dumps(rows[-1]), flush=True)
    print(table(rows))
    if args.out:
        Path(args.out).write_text(json.dumps({"server_args": args.server_arg, "rows": rows}, indent=1) + "\n")
    if args.fixture:
        update_fixture(args.fixture, rows)


if __name__ == "__main__":
    main()
