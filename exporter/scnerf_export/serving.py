"""The Rust server driven from Python: start the binary, wait until it is ready, send requests in
the API's own encodings. Used by the benchmark and by the tests that check the served renders."""

from __future__ import annotations

import base64
import io
import json
import os
import re
import subprocess
import time
import urllib.error
import urllib.request
import uuid
from pathlib import Path

import numpy as np
from PIL import Image

from .cameras import Camera, camera_json
from .runtime.view import Rendering

REPO = Path(__file__).resolve().parents[2]


def find_server_binary(explicit: str | Path | None = None) -> Path | None:
    """``explicit``, else the release build, else the debug build of this checkout, else None."""
    if explicit:
        return Path(explicit)
    for path in (REPO / "target/release/scnerf-server", REPO / "target/debug/scnerf-server"):
        if path.is_file():
            return path
    return None


class ServerProcess:
    """``scnerf-server`` on an ephemeral loopback port, ready (``/readyz`` 200) once constructed."""

    def __init__(
        self,
        binary: Path,
        bundle: str | Path,
        threads: int | None = None,
        extra: tuple[str, ...] = (),
        ready_timeout: float = 900.0,
    ):
        env = {**os.environ, "RUST_LOG": os.environ.get("RUST_LOG", "warn")}
        args = [str(binary), "--bundle", str(bundle), "--addr", "127.0.0.1:0", *extra]
        if threads:
            args += ["--threads", str(threads)]
        start = time.perf_counter()
        self.proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
        line = self.proc.stdout.readline()
        m = re.search(r"listening on (http://\S+)", line)
        if not m:
            raise RuntimeError(f"server did not start: {line!r} {self.proc.stderr.read()[-2000:]}")
        self.url = m.group(1)
        deadline = time.time() + ready_timeout
        while time.time() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"server exited: {self.proc.stderr.read()[-2000:]}")
            try:
                if self.request("GET", "/readyz")[0] == 200:
                    break
            except OSError:
                pass
            time.sleep(0.2)
        else:
            self.stop()
            raise RuntimeError(f"server not ready after {ready_timeout} s")
        self.startup_ms = (time.perf_counter() - start) * 1000.0
        self.model = json.loads(self.request("GET", "/v1/model")[1])

    def request(
        self, method: str, path: str, body: bytes | None = None, headers: dict | None = None, timeout: float = 3600.0
    ) -> tuple[int, bytes, dict]:
        return http_request(self.url, method, path, body, headers, timeout)

    def peak_rss_mib(self) -> float:
        for line in Path(f"/proc/{self.proc.pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
        return float("nan")

    def stop(self) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()

    def __enter__(self) -> "ServerProcess":
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


def http_request(
    url: str, method: str, path: str, body: bytes | None = None, headers: dict | None = None, timeout: float = 3600.0
) -> tuple[int, bytes, dict]:
    """Status, body and headers of one request; error statuses are answers, not exceptions."""
    req = urllib.request.Request(url + path, data=body, method=method, headers=headers or {})
    try:
        with urllib.request.urlopen(req, timeout=timeout) as resp:
            return resp.status, resp.read(), dict(resp.headers)
    except urllib.error.HTTPError as e:
        return e.code, e.read(), dict(e.headers)


class ServedBundle:
    """The bundle a running server serves, used like :class:`runtime.onnx_pipeline.OnnxBundle`: a scene is
    encoded once (``POST /v1/scenes``) and each target rendered from it (``/v1/scenes/{id}/render``)."""

    def __init__(self, url: str):
        self.url = url.rstrip("/")
        status, body, _ = http_request(self.url, "GET", "/v1/model")
        if status != 200:
            raise ValueError(f"{self.url}/v1/model answered {status}: {body[:200]!r}")
        self.manifest = json.loads(body)

    def _post_json(self, path: str, document: dict) -> dict:
        status, body, _ = http_request(
            self.url,
            "POST",
            path,
            json.dumps(document).encode(),
            {"content-type": "application/json", "accept": "application/json"},
        )
        if status not in (200, 201):
            raise ValueError(f"POST {path} answered {status}: {body[:500].decode(errors='replace')}")
        return json.loads(body)

    def encode_scene(self, images: np.ndarray, cameras: list[Camera], near: float, far: float, background) -> str:
        sources = [
            {"camera": camera_json(c), "image": base64.b64encode(png_bytes(im)).decode()}
            for im, c in zip(images, cameras)
        ]
        document = {
            "sources": sources,
            "near": float(near),
            "far": float(far),
            "background": [float(b) for b in background],
        }
        return self._post_json("/v1/scenes", document)["scene_id"]

    def render_target(
        self,
        scene_id: str,
        target: Camera,
        near: float,
        far: float,
        background=(0.0, 0.0, 0.0),
        chunk: int | None = None,
    ) -> Rendering:
        doc = self._post_json(
            f"/v1/scenes/{scene_id}/render", {"target": camera_json(target), "outputs": ["rgb", "depth", "opacity"]}
        )
        rgb = np.asarray(Image.open(io.BytesIO(base64.b64decode(doc["rgb"]["data"]))).convert("RGB"), np.float32)
        shape = (target.height, target.width)
        floats = {
            k: np.frombuffer(base64.b64decode(doc[k]["data"]), dtype="<f4").reshape(shape) for k in ("depth", "opacity")
        }
        return Rendering(rgb / 255.0, floats["depth"], floats["opacity"])


def png_bytes(image: np.ndarray) -> bytes:
    """An (H,W,3) float image in [0,1] as an 8-bit PNG."""
    out = io.BytesIO()
    Image.fromarray((np.clip(image, 0.0, 1.0) * 255.0).round().astype(np.uint8)).save(out, format="PNG")
    return out.getvalue()


def multipart(fields: list[tuple[str, str, bytes, str]]) -> tuple[bytes, str]:
    """A multipart/form-data body of (name, filename, data, content type) parts, and its type."""
    boundary = uuid.uuid4().hex
    parts = []
    for name, filename, data, ctype in fields:
        disp = f'form-data; name="{name}"' + (f'; filename="{filename}"' if filename else "")
        parts.append(
            f"--{boundary}\r\nContent-Disposition: {disp}\r\nContent-Type: {ctype}\r\n\r\n".encode() + data + b"\r\n"
        )
    return b"".join(parts) + f"--{boundary}--\r\n".encode(), f"multipart/form-data; boundary={boundary}"


def render_request(
    sources: list[tuple[Camera, bytes]],
    target: Camera,
    near: float,
    far: float,
    background=(0.0, 0.0, 0.0),
    outputs=("rgb",),
) -> bytes:
    """A ``POST /v1/render`` JSON body: encoded source images (PNG/JPEG bytes) with their cameras."""
    return json.dumps(
        {
            "sources": [{"camera": camera_json(c), "image": base64.b64encode(data).decode()} for c, data in sources],
            "target": camera_json(target),
            "near": float(near),
            "far": float(far),
            "background": [float(b) for b in background],
            "outputs": list(outputs),
        }
    ).encode()
