#!/usr/bin/env python3
"""The release binary against the fourth robustness probe's conditions of done (the models folder,
one model stalling the others, a NaN in a 200). Starts a server per check, with the flags the
check names, and prints one JSON line per check; exits 1 when one fails.

    loadtest/done-when.sh        # builds the release binary, then runs this

Checks:
  flood        tokens `flood` and `quiet`: 6 closed-loop clients of `flood` render 64x64 views
               without a deadline (a refused one tries again after --flood-retry-ms) while
               `quiet` renders one view after another, also without; each of quiet's views is
               answered 200 within 3x its time on the idle server (the median of 5 renders
               before the flood)
  budget_1024  `--memory-budget-mb 3000` and no other flag: a 1024x1024 view of a scene of the
               fixture case is admitted and answered 200 (the scene cache's share follows the
               budget instead of being set aside from it)
  nan_depths   near=2, far=2.0000001 (equal in float32): 422 naming the depth range
  folder       `--models DIR` holding a good bundle, a graph linked to /dev/zero, a renderer
               whose weights lie in weights.bin, 60 bundles whose manifests quote 900 kB and
               one 24 MB manifest, beside 40 links to the folder: the server starts; a reload
               answers in under 64 KiB (reasons clipped, the list bounded) with the peak resident
               set under the budget (2500 MiB); weights.bin truncated, a reload and a render of
               the good model still answer 200 and the process lives
"""

from __future__ import annotations

import argparse
import hashlib
import json
import multiprocessing
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from attacks import CASE, REPO, Server, multipart, result, status_mib

sys.path.insert(0, str(REPO / "exporter"))
from scnerf_export.export.manifest import Manifest  # noqa: E402  (the exporter's, for the model id)

PARITY = REPO / "tests/fixtures/parity/bundle"


class Process:
    """A scnerf-server started with ``args`` on a free loopback port, ready, stopped on exit."""

    def __init__(self, binary: Path, args: list, log: Path):
        self.log = open(log, "wb")
        self.proc = subprocess.Popen(
            [str(binary), "--addr", "127.0.0.1:0", *args], stdout=subprocess.PIPE, stderr=self.log
        )
        for line in self.proc.stdout:
            if line.startswith(b"listening on http://"):
                addr = line.decode().strip().removeprefix("listening on http://")
                break
        else:
            raise SystemExit(f"the server exited before listening (see {log})")
        self.server = Server(addr, self.proc.pid)
        deadline = time.monotonic() + 600
        while self.server.request("GET", "/readyz", timeout=5)[0] != 200:
            if self.proc.poll() is not None or time.monotonic() > deadline:
                raise SystemExit(f"the server did not become ready (see {log})")
            time.sleep(0.25)

    def __enter__(self) -> Server:
        return self.server

    def __exit__(self, *_):
        self.proc.terminate()
        self.proc.wait(timeout=60)
        self.log.close()


def scene_parts(request: dict) -> list:
    scene = {k: v for k, v in request.items() if k not in ("target", "outputs")}
    parts = [("request", None, json.dumps(scene).encode())]
    return parts + [(f"source_{i}", f"s{i}.png", (CASE / f"source_{i}.png").read_bytes()) for i in range(3)]


def create_scene(server: Server, headers: dict) -> str:
    body, ctype = multipart(scene_parts(json.loads((CASE / "request.json").read_text())))
    status, _, answer, _ = server.request("POST", "/v1/scenes", body, {"content-type": ctype, **headers})
    if status != 201:
        raise SystemExit(f"cannot create a scene: {status} {answer[:200]!r}")
    return json.loads(answer)["scene_id"]


def view_body(size: int) -> bytes:
    """The case's target at ``size`` x ``size`` (intrinsics scaled about pixel centres)."""
    t = dict(json.loads((CASE / "request.json").read_text())["target"])
    i, sx, sy = t["intrinsics"], size / t["width"], size / t["height"]
    t["intrinsics"] = {"fx": i["fx"] * sx, "fy": i["fy"] * sy, "cx": (i["cx"] + 0.5) * sx - 0.5}
    t["intrinsics"]["cy"] = (i["cy"] + 0.5) * sy - 0.5
    t.update(width=size, height=size)
    return json.dumps({"target": t, "outputs": ["rgb"]}).encode()


def render(server: Server, scene: str, body: bytes, headers: dict):
    path = f"/v1/scenes/{scene}/render"
    status, _, _, secs = server.request("POST", path, body, {"content-type": "application/json", **headers})
    return status, secs


def flood(addr: str, scene: str, retry_ms: int, stop, statuses):
    """6 clients of token ``flood`` rendering without pause; a refused one tries again after
    ``retry_ms``. In a process of its own, so that its threads do not hold the quiet client's
    interpreter lock."""
    server, body, headers = Server(addr, None), view_body(64), {"authorization": "Bearer flood"}

    def client():
        while not stop.is_set():
            status = render(server, scene, body, headers)[0]
            statuses.append(status)
            if status != 200:
                time.sleep(retry_ms / 1000)

    clients = [threading.Thread(target=client) for _ in range(6)]
    for c in clients:
        c.start()
    for c in clients:
        c.join()


def check_flood(binary: Path, bundle: list, out: Path, retry_ms: int) -> dict:
    args = [*bundle, "--auth-token", "flood", "--auth-token", "quiet"]
    with Process(binary, args, out / "flood.log") as server:
        quiet = {"authorization": "Bearer quiet"}
        scenes = {
            "flood": create_scene(server, {"authorization": "Bearer flood"}),
            "quiet": create_scene(server, quiet),
        }
        body = view_body(64)
        idle = [render(server, scenes["quiet"], body, quiet) for _ in range(5)]
        unloaded = statistics.median(secs for _, secs in idle)
        with multiprocessing.Manager() as manager:
            stop, flooded = manager.Event(), manager.list()
            addr = f"{server.host}:{server.port}"
            flooding = multiprocessing.Process(target=flood, args=(addr, scenes["flood"], retry_ms, stop, flooded))
            flooding.start()
            time.sleep(3)  # the flood's requests admitted before quiet's first
            loaded = [render(server, scenes["quiet"], body, quiet) for _ in range(10)]
            stop.set()
            flooding.join()
            flooded = list(flooded)
    slowest = max(secs for _, secs in loaded)
    counts = {str(s): flooded.count(s) for s in sorted(set(flooded), key=str)}
    return result(
        "flood",
        all(s == 200 for s, _ in idle + loaded) and slowest <= 3 * unloaded,
        unloaded_s=round(unloaded, 3),
        quiet_statuses=[s for s, _ in loaded],
        quiet_s=[round(secs, 3) for _, secs in loaded],
        slowest_over_unloaded=round(slowest / unloaded, 2),
        flood_retry_ms=retry_ms,
        flood_statuses=counts,
    )


def check_budget_1024(binary: Path, out: Path) -> list:
    with Process(binary, ["--memory-budget-mb", "3000"], out / "budget.log") as server:
        scene = create_scene(server, {})
        status, secs = render(server, scene, view_body(1024), {})
        hwm = server.hwm_mib()
        request = json.loads((CASE / "request.json").read_text())
        request.update(near=2.0, far=2.0000001)
        body, ctype = multipart([("request", None, json.dumps(request).encode())] + scene_parts(request)[1:])
        nan_status, _, answer, _ = server.request("POST", "/v1/render", body, {"content-type": ctype})
    field = json.loads(answer)["error"]["field"] if nan_status == 422 else None
    return [
        result("budget_1024", status == 200, status=status, secs=round(secs, 1), vm_hwm_mib=round(hwm)),
        result("nan_depths", nan_status == 422 and field in ("near", "far"), status=nan_status, field=field),
    ]


def copy_bundle(to: Path):
    shutil.copytree(PARITY, to)


def with_external_weights(dir: Path):
    """The renderer with an initializer kept in weights.bin appended (protobuf merges it into the
    graph: ModelProto.graph > GraphProto.initializer > TensorProto name, external_data,
    data_location = EXTERNAL), its hash and the model id updated."""

    def field(tag: int, data: bytes) -> bytes:
        return bytes([tag, len(data)]) + data

    entry = field(0x0A, b"location") + field(0x12, b"weights.bin")
    tensor = field(0x42, b"extra") + field(0x6A, entry) + bytes([0x70, 1])
    renderer = dir / "renderer.onnx"
    renderer.write_bytes(renderer.read_bytes() + field(0x3A, field(0x2A, tensor)))
    (dir / "weights.bin").write_bytes(bytes(1 << 16))
    manifest = Manifest.load(dir)
    manifest.graphs["renderer"].sha256 = hashlib.sha256(renderer.read_bytes()).hexdigest()
    manifest.model_id = manifest.expected_model_id()
    manifest.save(dir)


def hostile_folder(root: Path) -> Path:
    models = root / "models"
    copy_bundle(models / "good")
    copy_bundle(models / "zero")
    (models / "zero/renderer.onnx").unlink()
    (models / "zero/renderer.onnx").symlink_to("/dev/zero")
    copy_bundle(models / "external")
    with_external_weights(models / "external")
    manifest = json.loads((PARITY / "manifest.json").read_text())
    for i in range(60):
        (models / f"quoting{i}").mkdir()
        (models / f"quoting{i}/manifest.json").write_text(json.dumps({**manifest, "variant": "v" * 900_000}))
    (models / "huge").mkdir()
    (models / "huge/manifest.json").write_text(json.dumps({**manifest, "pad": "x" * 24_000_000}))
    for i in range(40):
        (models / f"self{i}").symlink_to(".")
    return models


def check_folder(binary: Path, out: Path) -> dict:
    with tempfile.TemporaryDirectory(prefix="scnerf-done-when-") as tmp:
        models = hostile_folder(Path(tmp))
        started = time.perf_counter()
        args = ["--models", str(models), "--memory-budget-mb", "2500"]
        with Process(binary, args, out / "folder.log") as server:
            ready_s = time.perf_counter() - started
            status, _, answer, secs = server.request("POST", "/v1/models/reload")
            reloaded = json.loads(answer) if status == 200 else {}
            reasons = {s["name"]: s["reason"] for s in reloaded.get("skipped", [])}
            os.truncate(models / "external/weights.bin", 0)
            again = server.request("POST", "/v1/models/reload")[0]
            scene = create_scene(server, {})
            after = render(server, scene, view_body(64), {})[0]
            hwm = server.hwm_mib()
            alive = server.request("GET", "/healthz")[0] == 200 and status_mib(server.pid, "VmRSS") > 0
    ok = (
        status == 200
        and len(answer) < 64 << 10
        and "is not a regular file" in reasons.get("zero", "")
        and "external file" in reasons.get("external", "")
        and hwm < 2500
        and again == 200
        and after == 200
        and alive
    )
    return result(
        "folder",
        ok,
        ready_s=round(ready_s, 1),
        reload_status=status,
        reload_s=round(secs, 2),
        answer_bytes=len(answer),
        skipped_listed=len(reasons),
        skipped_more=reloaded.get("skipped_more"),
        reasons={k: reasons.get(k, "")[:120] for k in ("zero", "external", "quoting0", "huge")},
        after_truncation=[again, after],
        vm_hwm_mib=round(hwm),
    )


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--binary", type=Path, default=REPO / "target/release/scnerf-server")
    parser.add_argument("--bundle", type=Path, default=REPO / "bundles/default", help="the flood's bundle")
    parser.add_argument("--out", type=Path, default=REPO / "target/loadtest")
    parser.add_argument("--only", default="flood,budget_1024,folder")
    parser.add_argument("--flood-retry-ms", type=int, default=50, help="the flood's pause after a refusal")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    checks = {
        "flood": lambda: [check_flood(args.binary, ["--bundle", str(args.bundle)], args.out, args.flood_retry_ms)],
        "budget_1024": lambda: check_budget_1024(args.binary, args.out),
        "folder": lambda: [check_folder(args.binary, args.out)],
    }
    failed = 0
    for name in args.only.split(","):
        for line in checks[name]():
            print(json.dumps(line), flush=True)
            failed += not line["ok"]
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
