#!/usr/bin/env python3
"""The hostile clients of the robustness probe, against a running scnerf-server, each with the
answer it must get; renders of a cached scene run beside them, and the server's peak resident set
(VmHWM) must stay within its memory budget throughout.

    loadtest/attacks.sh                      # short form (CI): parity bundle, debug build
    SCALE=full PROFILE=release BUNDLE=bundles/default \\
        SERVER_ARGS="--memory-budget-mb 3000" loadtest/attacks.sh   # the probe's sizes

Attacks (full size; the short form shrinks the sizes and counts):
  captures      4 concurrent captures of 64 flat 1024x1024 PNGs: 201, or 503 / 422 before decoding
  scenes        2 concurrent POST /v1/scenes of 64 JSON (base64) sources of 1024x1024: likewise
  json_zeros    a transforms.json of [0,0,...] (60 MiB): 422 at the value cap, quickly
  newlines      a COLMAP cameras.txt of 60 MiB of newlines: 422; 128 MiB: 413 at the metadata cap
  npy           poses_bounds.npy declaring (1085102592571150096, 17): 422, not 500
  dtu           8,000 files under Rectified/ with a 5 s deadline: 201 (detection is linear)
  connections   one address opens 600 keep-alive connections: refused past its cap (429), and
                /healthz from another address answers within 1 s
  deadline      4 MiB declared, 1 MiB sent, a 2 s deadline: 504 within 1 s of the deadline
  stalled       8 uploads of 250 MiB from one address, stalled at 240 MiB: held against the budget,
                503 past it, 408 at the stall limit
  spray         260 connections from 10 addresses sending 2 MiB once: each answered by the stall
                limit (+2 s); another client's POST meanwhile is not refused for want of slots
                after that
  methods       20,000 requests with distinct 15 KB method names: /metrics gains no series
  image_bombs   8 concurrent scenes of 3 PNGs whose colour profile and zTXt chunk each inflate to
                1 GiB (1 MB sent): 201, or 429 / 503 for load, within the budget (the header
                reader skips them)
Then `together`: captures, json_zeros, stalled and renders at once (VmHWM within the budget).

Prints one JSON line per attack and exits 1 when one does not get its answer.

``--soak-secs N`` soaks instead (loadtest/soak-mixed.sh): renders without pause and, in turn, each
hostile client above and a capture uploaded, rendered and deleted, for N s; the server's RSS outside
its scene cache must stay flat (at most ``--max-growth-pct`` above where it was after the first
fifth).
"""

from __future__ import annotations

import argparse
import base64
import functools
import io
import json
import socket
import sys
import threading
import time
import zlib
from pathlib import Path

import numpy as np
from PIL import Image

REPO = Path(__file__).resolve().parent.parent
CASE = REPO / "tests/fixtures/parity/cases/opencv_64x96"
DATASETS = REPO / "tests/fixtures/datasets"
BOUNDARY = "scnerf-attack-5c1e"

SIZES = {
    # name: full, short
    "views": (64, 12),
    "image": (1024, 128),
    "captures": (4, 2),
    "metadata_mib": (60, 6),
    "over_cap_mib": (128, 70),
    "dtu_files": (8000, 8000),
    "connections": (600, 80),
    "stalled": (8, 3),
    "stalled_mib": (240, 90),
    "spray": (260, 40),
    "methods": (20000, 1000),
    "method_bytes": (15000, 100),
    "bombs": (8, 4),
    "bomb_mib": (1024, 256),
}


class Server:
    def __init__(self, addr: str, pid: int | None):
        host, port = addr.rsplit(":", 1)
        self.host, self.port, self.pid = host, int(port), pid
        self.peak_mib = 0.0

    def hwm_mib(self) -> float:
        return status_mib(self.pid, "VmHWM") if self.pid else 0.0

    def connect(self, ip: str = "127.0.0.1", timeout: float = 30.0) -> socket.socket:
        s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        s.bind((ip, 0))
        s.settimeout(timeout)
        s.connect((self.host, self.port))
        return s

    def request(self, method, path, body=b"", headers=None, ip="127.0.0.1", timeout=600.0):
        """(status, headers text, body, seconds); status None when no answer came."""
        started = time.perf_counter()
        try:
            s = self.connect(ip, timeout)
            head = f"{method} {path} HTTP/1.1\r\nHost: x\r\nConnection: close\r\nContent-Length: {len(body)}\r\n"
            head += "".join(f"{k}: {v}\r\n" for k, v in (headers or {}).items())
            s.sendall(head.encode() + b"\r\n" + body)
            data = read_all(s)
        except OSError as e:
            return None, str(e), b"", time.perf_counter() - started
        return (*parse(data), time.perf_counter() - started)

    def metric(self, name: str) -> float | None:
        """A value of ``/metrics`` (``scnerf_`` + name), None when absent or unreachable."""
        status, _, body, _ = self.request("GET", "/metrics", timeout=10)
        for line in body.decode("utf-8", "replace").splitlines() if status == 200 else []:
            if line.startswith(f"scnerf_{name} "):
                return float(line.split()[1])
        return None


def read_all(s: socket.socket) -> bytes:
    chunks = []
    while True:
        try:
            chunk = s.recv(1 << 16)
        except (ConnectionResetError, TimeoutError):
            break
        if not chunk:
            break
        chunks.append(chunk)
    s.close()
    return b"".join(chunks)


def parse(data: bytes):
    head, _, body = data.partition(b"\r\n\r\n")
    lines = head.decode("latin-1").split("\r\n")
    try:
        status = int(lines[0].split()[1])
    except (IndexError, ValueError):
        return None, head.decode("latin-1"), body
    return status, "\n".join(lines[1:]).lower(), body


def status_within(s: socket.socket, timeout: float):
    """The status of the answer on ``s`` if one comes within ``timeout`` s, and when."""
    started = time.perf_counter()
    s.settimeout(timeout)
    try:
        data = s.recv(4096)
    except OSError:
        return None, time.perf_counter() - started
    status = parse(data)[0] if data else None
    return status, time.perf_counter() - started


def multipart(parts) -> tuple[bytes, str]:
    """parts: (name, filename or None, bytes)."""
    out = io.BytesIO()
    for name, filename, data in parts:
        out.write(f"--{BOUNDARY}\r\n".encode())
        disposition = f'form-data; name="{name}"' + (f'; filename="{filename}"' if filename else "")
        out.write(f"Content-Disposition: {disposition}\r\nContent-Type: application/octet-stream\r\n\r\n".encode())
        out.write(data)
        out.write(b"\r\n")
    out.write(f"--{BOUNDARY}--\r\n".encode())
    return out.getvalue(), f"multipart/form-data; boundary={BOUNDARY}"


def flat_png(size: int, shade: int) -> bytes:
    out = io.BytesIO()
    Image.fromarray(np.full((size, size, 3), shade, np.uint8)).save(out, "PNG")
    return out.getvalue()


def blender_capture(views: int, size: int) -> list:
    matrix = json.loads((DATASETS / "blender/transforms_train.json").read_text())["frames"][0]["transform_matrix"]
    frames = [{"file_path": f"./train/r_{i}", "transform_matrix": matrix} for i in range(views)]
    files = [("file", "transforms_train.json", json.dumps({"camera_angle_x": 0.69, "frames": frames}).encode())]
    png = flat_png(size, 128)
    return files + [("file", f"train/r_{i}.png", png) for i in range(views)]


def fixture_files(folder: str) -> list:
    root = DATASETS / folder
    return [
        ("file", str(p.relative_to(root)), p.read_bytes())
        for p in sorted(root.rglob("*"))
        if p.is_file() and p.name != "expected.json"
    ]


def upload(server: Server, files: list, headers=None, ip="127.0.0.1"):
    body, ctype = multipart(files)
    return server.request("POST", "/v1/captures", body, {"content-type": ctype, **(headers or {})}, ip=ip)


def result(name: str, ok: bool, **details) -> dict:
    return {"attack": name, "ok": bool(ok), **details}


def size(args, key):
    return SIZES[key][0 if args.scale == "full" else 1]


def attack_captures(server, args):
    files = blender_capture(size(args, "views"), size(args, "image"))
    answers = parallel([lambda: upload(server, files)] * size(args, "captures"))
    statuses = [a[0] for a in answers]
    return result(
        "captures",
        all(s in (201, 422, 503) for s in statuses),
        statuses=statuses,
        seconds=[round(a[3], 2) for a in answers],
    )


def attack_scenes(server, args):
    views, side = size(args, "views"), size(args, "image")
    request = json.loads((CASE / "request.json").read_text())
    png = base64.b64encode(flat_png(side, 90)).decode()
    camera = dict(request["sources"][0]["camera"])
    scale = side / camera["width"]
    camera.update(width=side, height=side)
    i = camera["intrinsics"]
    camera["intrinsics"] = {"fx": i["fx"] * scale, "fy": i["fy"] * scale, "cx": side / 2 - 0.5, "cy": side / 2 - 0.5}
    body = json.dumps({"sources": [{"camera": camera, "image": png}] * views, "near": 2.0, "far": 6.0}).encode()
    answers = parallel([lambda: server.request("POST", "/v1/scenes", body, {"content-type": "application/json"})] * 2)
    statuses = [a[0] for a in answers]
    return result("scenes", all(s in (201, 422, 503) for s in statuses), statuses=statuses)


def attack_json_zeros(server, args, busy_ok=False):
    """``busy_ok``: beside uploads that hold the budget, 503 before the parse is right too."""
    n = size(args, "metadata_mib") << 20
    text = b'{"camera_angle_x": 0.7, "frames": [], "x": [' + b"0," * (n // 2 - 40) + b"0]}"
    files = [("file", "transforms_train.json", text)] + blender_capture(3, 16)[1:]
    status, _, body, secs = upload(server, files)
    ok = (status == 422 and b"values" in body) or (busy_ok and status == 503)
    return result("json_zeros", ok, status=status, seconds=round(secs, 2))


def attack_newlines(server, args):
    colmap = [f for f in fixture_files("colmap") if not f[1].endswith("cameras.txt")]
    answers = {}
    for key, expect in (("metadata_mib", 422), ("over_cap_mib", 413)):
        text = b"\n" * (size(args, key) << 20)
        status, _, _, secs = upload(server, colmap + [("file", "sparse/0/cameras.txt", text)])
        answers[key] = (status, expect, round(secs, 2))
    return result("newlines", all(s == e for s, e, _ in answers.values()), answers=answers)


def attack_npy(server, _args):
    header = "{'descr': '<f8', 'fortran_order': False, 'shape': (1085102592571150096, 17), }"
    npy = b"\x93NUMPY\x01\x00" + len(header).to_bytes(2, "little") + header.encode() + bytes(128)
    files = [f for f in fixture_files("llff") if f[1] != "poses_bounds.npy"] + [("file", "poses_bounds.npy", npy)]
    status, _, body, _ = upload(server, files)
    return result("npy", status == 422, status=status, body=body[:160].decode(errors="replace"))


def attack_dtu(server, args):
    junk = [("file", f"Rectified/junk_{i:05}.txt", b"x") for i in range(size(args, "dtu_files"))]
    files = fixture_files("dtu") + junk
    status, _, _, secs = upload(server, files, {"x-scnerf-deadline-ms": "5000"})
    return result("dtu", status == 201, status=status, seconds=round(secs, 2))


def attack_connections(server, args):
    held, refused = [], 0
    for _ in range(size(args, "connections")):
        try:
            s = server.connect("127.0.0.2", 5)
        except OSError:
            refused += 1
            continue
        s.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n")
        status, _ = status_within(s, 5)
        if status == 200:
            held.append(s)
        else:
            refused += 1
            s.close()
    status, _, _, secs = server.request("GET", "/healthz", ip="127.0.0.3", timeout=5)
    for s in held:
        s.close()
    return result(
        "connections",
        status == 200 and secs < 1.0 and refused > 0,
        held=len(held),
        refused=refused,
        healthz_status=status,
        healthz_seconds=round(secs, 3),
    )


def stalled_post(server, ip, path, length, sent, headers="", part=b""):
    """A POST of ``length`` bytes that sends ``part`` (a multipart part's head) and ``sent`` bytes
    of padding, then nothing."""
    s = server.connect(ip, 60)
    head = f"POST {path} HTTP/1.1\r\nHost: x\r\nContent-Type: multipart/form-data; boundary=x\r\n{headers}"
    s.sendall(f"{head}Content-Length: {length}\r\n\r\n".encode())
    try:
        s.sendall(part + b" " * sent)
    except OSError:
        pass  # refused while sending: the answer is waiting
    return s


def attack_deadline(server, _args):
    started = time.perf_counter()
    s = stalled_post(server, "127.0.0.4", "/v1/render", 4 << 20, 1 << 20, "x-scnerf-deadline-ms: 2000\r\n")
    status, _ = status_within(s, 10)
    took = time.perf_counter() - started
    s.close()
    return result("deadline", status == 504 and took < 3.0, status=status, seconds=round(took, 2))


def attack_stalled(server, args, during=None):
    mib = size(args, "stalled_mib")

    def one():
        started = time.perf_counter()
        part = b'--x\r\nContent-Disposition: form-data; name="file"; filename="images/a.png"\r\n\r\n'
        s = stalled_post(server, "127.0.0.5", "/v1/captures", 250 << 20, mib << 20, part=part)
        status, _ = status_within(s, 30)
        s.close()
        return status, time.perf_counter() - started

    threads = [lambda: one()] * size(args, "stalled")
    if during:
        threads.append(during)
    answers = parallel(threads)
    statuses = [a[0] for a in answers[: size(args, "stalled")]]
    # Each is refused (503) once the budget is held, or times out at the stall limit (408).
    return result("stalled", all(s in (408, 503) for s in statuses), statuses=statuses)


def attack_spray(server, args, stall_secs):
    count = size(args, "spray")

    def one(i):
        started = time.perf_counter()
        s = stalled_post(server, f"127.0.1.{i % 10 + 1}", "/v1/render", 60 << 20, 2 << 20)
        status, _ = status_within(s, stall_secs + 30)
        s.close()
        return status, time.perf_counter() - started

    results = []
    threads = [threading.Thread(target=lambda i=i: results.append(one(i))) for i in range(count)]
    for t in threads:
        t.start()
    time.sleep(stall_secs + 3)
    other = server.request(
        "POST", "/v1/scenes/unknown/render", b"{}", {"content-type": "application/json"}, ip="127.0.2.1", timeout=10
    )
    for t in threads:
        t.join()
    late = [r for r in results if r[0] is None or r[1] > stall_secs + 3]
    return result(
        "spray",
        not late and other[0] not in (None, 503),
        statuses=sorted({r[0] for r in results}, key=str),
        slowest_seconds=round(max(r[1] for r in results), 1),
        other_client_status=other[0],
    )


def request_series(server) -> int | None:
    """How many ``scnerf_http_requests_total`` series ``/metrics`` holds (None: no answer)."""
    status, _, body, _ = server.request("GET", "/metrics", timeout=60)
    if status != 200:
        return None
    return sum(line.startswith(b"scnerf_http_requests_total{") for line in body.splitlines())


def attack_methods(server, args):
    """Any token is a method: each distinct one must not become a metric series of its own."""
    pad = "X" * size(args, "method_bytes")
    server.request("WARMUP", "/healthz")  # the series of unknown methods, once
    request_series(server)  # and that of /metrics, counted once a scrape is answered
    before = request_series(server)
    statuses = set()
    for i in range(size(args, "methods")):
        statuses.add(server.request(f"M{i:06}{pad}", "/healthz")[0])
    after = request_series(server)
    return result(
        "methods", before is not None and after == before, series=[before, after], statuses=sorted(statuses, key=str)
    )


def png_with_chunks(png: bytes, chunks) -> bytes:
    """``png`` with ``chunks`` (type, data) between its header (IHDR) and its image data."""
    out = png[:33]
    for kind, data in chunks:
        out += len(data).to_bytes(4, "big") + kind + data + zlib.crc32(kind + data).to_bytes(4, "big")
    return out + png[33:]


@functools.cache
def zlib_zeros(mib: int) -> bytes:
    z = zlib.compressobj(9)
    block = bytes(1 << 20)
    return b"".join(z.compress(block) for _ in range(mib)) + z.flush()


def attack_image_bombs(server, args):
    """Scenes of the parity sources, each carrying a colour profile and a zTXt chunk that inflate
    to ``bomb_mib``: read without inflating them."""
    zeros = zlib_zeros(size(args, "bomb_mib"))
    chunks = [(b"iCCP", b"bomb\0\0" + zeros), (b"zTXt", b"Comment\0\0" + zeros)]
    request = json.loads((CASE / "request.json").read_text())
    scene = {k: v for k, v in request.items() if k not in ("target", "outputs")}
    parts = [("request", None, json.dumps(scene).encode())]
    for i in range(3):
        parts.append((f"source_{i}", f"s{i}.png", png_with_chunks((CASE / f"source_{i}.png").read_bytes(), chunks)))
    body, ctype = multipart(parts)

    def one():
        # A deadline of the client's lets the scenes queue (and decode) together.
        headers = {"content-type": ctype, "x-scnerf-deadline-ms": "600000"}
        return server.request("POST", "/v1/scenes", body, headers)

    answers = parallel([one] * size(args, "bombs"))
    statuses = [a[0] for a in answers]
    return result(
        "image_bombs",
        201 in statuses and all(s in (201, 429, 503) for s in statuses),
        statuses=statuses,
        seconds=[round(a[3], 2) for a in answers],
    )


def parallel(calls: list) -> list:
    out = [None] * len(calls)

    def run(i):
        out[i] = calls[i]()

    threads = [threading.Thread(target=run, args=(i,)) for i in range(len(calls))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return out


class Renders:
    """Renders of a cached scene in a loop while attacks run: their statuses and latencies."""

    def __init__(self, server: Server, target: int):
        request = json.loads((CASE / "request.json").read_text())
        scene = {k: v for k, v in request.items() if k not in ("target", "outputs")}
        parts = [("request", None, json.dumps(scene).encode())]
        parts += [(f"source_{i}", f"s{i}.png", (CASE / f"source_{i}.png").read_bytes()) for i in range(3)]
        body, ctype = multipart(parts)
        status, _, answer, _ = server.request("POST", "/v1/scenes", body, {"content-type": ctype})
        if status != 201:
            raise SystemExit(f"cannot create the render scene: {status} {answer[:200]!r}")
        self.path = f"/v1/scenes/{json.loads(answer)['scene_id']}/render"
        t = dict(request["target"])
        scale = target / t["width"]
        i = t["intrinsics"]
        t["intrinsics"] = {k: i[k] * scale for k in ("fx", "fy")} | {"cx": (i["cx"] + 0.5) * scale - 0.5}
        t["intrinsics"]["cy"] = (i["cy"] + 0.5) * (target / t["height"]) - 0.5
        t.update(width=target, height=target)
        self.body = json.dumps({"target": t, "outputs": ["rgb"]}).encode()
        self.server, self.samples, self.stop = server, [], threading.Event()

    def run(self):
        while not self.stop.is_set():
            status, _, _, secs = self.server.request("POST", self.path, self.body, {"content-type": "application/json"})
            self.samples.append((status, secs))

    def summary(self) -> dict:
        statuses: dict = {}
        for s, _ in self.samples:
            statuses[str(s)] = statuses.get(str(s), 0) + 1
        ok = sorted(t for s, t in self.samples if s == 200)
        return {"statuses": statuses, "p50_200_s": round(ok[len(ok) // 2], 2) if ok else None}


def capture_round(server, args) -> int | None:
    """A capture uploaded, one view of it rendered, the scene deleted: the render's status (None
    when the upload or the render was refused for load: 503, or 429 for the render's wait)."""
    status, _, body, _ = upload(server, blender_capture(8, 128))
    if status == 503:
        return None
    if status != 201:
        return status
    created = json.loads(body)
    camera = created["cameras"][0]
    scale = args.render_size / camera["width"]
    i = camera["intrinsics"]
    camera["intrinsics"] = {"fx": i["fx"] * scale, "fy": i["fy"] * scale}
    camera["intrinsics"] |= {"cx": (i["cx"] + 0.5) * scale - 0.5, "cy": (i["cy"] + 0.5) * scale - 0.5}
    camera.update(width=args.render_size, height=args.render_size)
    path = f"/v1/scenes/{created['scene_id']}"
    rendered = server.request(
        "POST", f"{path}/render", json.dumps({"target": camera}).encode(), {"content-type": "application/json"}
    )
    server.request("DELETE", path)
    return None if rendered[0] == 429 else rendered[0]


def status_mib(pid: int, field: str) -> float:
    """A memory field of /proc/PID/status (VmRSS, VmHWM), in MiB; 0 when absent."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(f"{field}:"):
            return int(line.split()[1]) / 1024
    return 0.0


def soak(server, args, attacks, renders) -> int:
    """Renders without pause; in turn, one hostile client and one capture round; the server's RSS
    and its scene cache's bytes after each turn. Passes when every attack got its answer and the
    RSS outside the scene cache (which holds what the clients uploaded, bounded by
    ``--scene-cache-mb`` and emptied by the TTL) grew by at most ``--max-growth-pct`` from the end
    of the first fifth (warm-up) to the end, each the median of three samples."""
    names = [n for n in attacks if n not in ("captures", "scenes")]
    loop = threading.Thread(target=renders.run)
    loop.start()
    started, series, failed, turns, captures = time.perf_counter(), [], [], 0, {}
    while time.perf_counter() - started < args.soak_secs:
        row = attacks[names[turns % len(names)]]()
        if not row["ok"]:
            failed.append(row)
        status = capture_round(server, args)
        captures[str(status)] = captures.get(str(status), 0) + 1
        turns += 1
        time.sleep(2)
        cached = (server.metric("scene_cache_bytes") or 0) / 2**20
        series.append(
            (round(time.perf_counter() - started), round(status_mib(server.pid, "VmRSS"), 1), round(cached, 1))
        )
    renders.stop.set()
    loop.join()
    values = [rss - cached for _, rss, cached in series]
    warm_at = max(1, len(values) // 5)
    warm = sorted(values[warm_at - 1 : warm_at + 2])[1] if len(values) >= 3 else values[0]
    end = sorted(values[-3:])[len(values[-3:]) // 2]
    growth = 100 * (end - warm) / warm
    rss = [r for _, r, _ in series]
    ok = not failed and growth <= args.max_growth_pct and all(s in ("200", "None") for s in captures)
    print(
        json.dumps(
            {
                "soak_s": round(time.perf_counter() - started),
                "turns": turns,
                "failed_attacks": failed,
                "capture_rounds": captures,
                "renders": renders.summary(),
                "rss_mib": {"start": rss[0], "end": rss[-1], "max": max(rss)},
                "outside_cache_mib": {"start": values[0], "after_warmup": warm, "end": end, "max": max(values)},
                "growth_after_warmup_pct": round(growth, 2),
                "server_vmhwm_mib": round(server.hwm_mib()),
                "rss_series": series,
                "ok": ok,
            }
        ),
        flush=True,
    )
    return 0 if ok else 1


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--addr", required=True)
    parser.add_argument("--pid", type=int, default=None, help="the server's pid, for its VmHWM")
    parser.add_argument("--scale", choices=("short", "full"), default="short")
    parser.add_argument("--budget-mb", type=float, default=None, help="VmHWM must stay under it")
    parser.add_argument("--stall-secs", type=float, default=10.0, help="the server's --body-stall-secs")
    parser.add_argument("--render-size", type=int, default=16)
    parser.add_argument("--only", default="", help="comma-separated attack names")
    parser.add_argument("--soak-secs", type=float, default=0, help="soak this long instead (see soak())")
    parser.add_argument("--max-growth-pct", type=float, default=5.0)
    args = parser.parse_args(argv)
    server = Server(args.addr, args.pid)
    renders = Renders(server, args.render_size)
    attacks = {
        "captures": lambda: attack_captures(server, args),
        "scenes": lambda: attack_scenes(server, args),
        "json_zeros": lambda: attack_json_zeros(server, args),
        "newlines": lambda: attack_newlines(server, args),
        "npy": lambda: attack_npy(server, args),
        "dtu": lambda: attack_dtu(server, args),
        "connections": lambda: attack_connections(server, args),
        "deadline": lambda: attack_deadline(server, args),
        "stalled": lambda: attack_stalled(server, args),
        "spray": lambda: attack_spray(server, args, args.stall_secs),
        "methods": lambda: attack_methods(server, args),
        "image_bombs": lambda: attack_image_bombs(server, args),
    }
    if args.soak_secs:
        return soak(server, args, attacks, renders)
    only = [a for a in args.only.split(",") if a] or [*attacks, "together"]
    failed = 0
    for name in only:
        if name == "together":
            loop = threading.Thread(target=renders.run)
            loop.start()
            answers = parallel(
                [
                    attacks["captures"],
                    lambda: attack_json_zeros(server, args, True),
                    lambda: attack_stalled(server, args),
                ]
            )
            renders.stop.set()
            loop.join()
            row = result("together", all(a["ok"] for a in answers), parts=answers, renders=renders.summary())
        else:
            row = attacks[name]()
        hwm = server.hwm_mib()
        row["server_vmhwm_mib"] = round(hwm)
        if args.budget_mb and hwm > args.budget_mb:
            row["ok"] = False
        alive = server.request("GET", "/healthz", timeout=10)[0] == 200
        row["ok"] = row["ok"] and alive
        failed += not row["ok"]
        print(json.dumps(row), flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
