"""The Rust server driven from Python: start the binary and wait until it is ready; requests go
through the project's Python client (``scnerf_client``). Used by the benchmark and by the tests
and evaluations that check the served renders."""

from __future__ import annotations

import io
import os
import re
import subprocess
import time
from pathlib import Path

import numpy as np
from PIL import Image

from scnerf_client import Client

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
    """``scnerf-server`` on an ephemeral loopback port, ready (``/readyz`` 200) once constructed;
    ``client`` talks to it."""

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
        self.client = Client(self.url)
        deadline = time.time() + ready_timeout
        while not self.client.ready():
            if self.proc.poll() is not None:
                raise RuntimeError(f"server exited: {self.proc.stderr.read()[-2000:]}")
            if time.time() > deadline:
                self.stop()
                raise RuntimeError(f"server not ready after {ready_timeout} s")
            time.sleep(0.2)
        self.startup_ms = (time.perf_counter() - start) * 1000.0
        self.model = self.client.model()

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


class ServedBundle:
    """The bundle a running server serves, used like :class:`runtime.onnx_pipeline.OnnxBundle`: a scene is
    encoded once (``PUT /v1/scenes/{id}``) and each target rendered from it (``/v1/scenes/{id}/render``)."""

    def __init__(self, url: str):
        self.client = Client(url)
        self.model = self.client.model()
        self.scenes: dict = {}

    @property
    def model_id(self) -> str:
        return self.model["model_id"]

    def encode_scene(self, images: np.ndarray, cameras: list[Camera], near: float, far: float, background) -> str:
        scene = self.client.upload_scene(list(images), [camera_json(c) for c in cameras], near, far, background)
        self.scenes[scene.id] = scene
        return scene.id

    def render_target(
        self,
        scene_id: str,
        target: Camera,
        near: float,
        far: float,
        background=(0.0, 0.0, 0.0),
        chunk: int | None = None,
    ) -> Rendering:
        r = self.client.render_scene(self.scenes.get(scene_id, scene_id), camera_json(target))
        return Rendering(r.rgb, r.depth, r.opacity)


def png_bytes(image: np.ndarray) -> bytes:
    """An (H,W,3) float image in [0,1] as an 8-bit PNG."""
    out = io.BytesIO()
    Image.fromarray((np.clip(image, 0.0, 1.0) * 255.0).round().astype(np.uint8)).save(out, format="PNG")
    return out.getvalue()
