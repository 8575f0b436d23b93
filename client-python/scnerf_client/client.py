"""``Client``: scnerf-serve's API from Python, answers as numpy arrays.

Waits out 503/429 for their ``Retry-After`` (as the ``scnerf`` command line does); a render of a
scene the server no longer holds (404 with the hint ``reupload``: expired, evicted, its server
restarted) uploads the scene again once, under the same id, and renders again."""

from __future__ import annotations

import hashlib
import json
import re
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import requests

from . import captures
from .cameras import CameraLike, camera_json
from .errors import CaptureError, ConnectionFailed, SceneNotFound, server_error
from .images import ImageLike, decode_floats, decode_rgb, encoded

Outputs = Sequence[str]
ALL_OUTPUTS = ("rgb", "depth", "opacity")


@dataclass(frozen=True)
class Limits:
    """What the server accepts (``GET /v1/limits``)."""

    max_source_pixels: int
    max_target_pixels: int
    max_scene_views: int
    max_body_bytes: int
    max_capture_bytes: int
    max_json_bytes: int


@dataclass
class Rendering:
    """A rendered view: ``rgb`` (H, W, 3) float32 in [0, 1], ``depth`` and ``opacity`` (H, W)
    float32 when asked for, the server's stage ``timings`` in ms, the source views it used, and how
    its rays were sampled (``full`` or ``guided``) with the network samples per pixel."""

    rgb: np.ndarray | None
    depth: np.ndarray | None
    opacity: np.ndarray | None
    timings: dict[str, float]
    model_id: str
    sources: list[int] | None = None
    sampling: str | None = None
    samples_per_ray: float | None = None
    #: The name of the model that rendered it (``GET /v1/models``).
    model: str | None = None

    def __repr__(self) -> str:
        image = next(a for a in (self.rgb, self.depth, self.opacity, np.zeros((0, 0))) if a is not None)
        outputs = "+".join(n for n in ("rgb", "depth", "opacity") if getattr(self, n) is not None) or "nothing"
        sampled = f", {self.sampling} {self.samples_per_ray:.1f} samples/ray" if self.sampling else ""
        return f"Rendering({image.shape[1]}x{image.shape[0]} {outputs}, sources {self.sources}{sampled})"


@dataclass
class Scene:
    """A scene the server holds: its id, cameras (API JSON, in the order of view indices) and
    depth range; for a capture also its view names, format, image set, the notes of the server's
    plan of what was sent (the image set picked and why, images resized first, files left out) and
    the warnings of its reading."""

    id: str
    cameras: list[dict[str, Any]]
    near: float
    far: float
    names: list[str] = field(default_factory=list)
    #: The server's stage timings of the upload in ms (its ``server-timing`` header).
    timings: dict[str, float] = field(default_factory=dict)
    format: str | None = None
    image_set: str | None = None
    warnings: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    #: The model the scene belongs to: its renders use it.
    model: str | None = None
    upload: Callable[[], str] | None = field(default=None, repr=False)

    def __repr__(self) -> str:
        sizes = sorted({(c["width"], c["height"]) for c in self.cameras})
        size = ", ".join(f"{w}x{h}" for w, h in sizes) or "no views"
        what = ", ".join(str(p) for p in (self.format, self.image_set) if p)
        warned = f", {len(self.warnings)} warnings" if self.warnings else ""
        return (
            f"Scene({self.id!r}, {what + ', ' if what else ''}{len(self.cameras)} views at {size}, "
            f"near {self.near:g} far {self.far:g}{warned})"
        )


class Client:
    """``Client("http://127.0.0.1:8080", token=None)``."""

    def __init__(self, url: str, token: str | None = None, timeout: float = 3600.0, max_retries: int = 30):
        self.url = url.rstrip("/")
        self.timeout, self.max_retries = timeout, max_retries
        self.session = requests.Session()
        self.session.headers["Accept"] = "application/json"
        if token:
            self.session.headers["Authorization"] = f"Bearer {token}"
        self._limits: Limits | None = None

    # -- the service

    def ready(self) -> bool:
        """Whether the server has its model loaded and warmed up (``GET /readyz``)."""
        try:
            return self.session.get(self.url + "/readyz", timeout=self.timeout).status_code == 200
        except requests.ConnectionError:
            return False

    def metrics(self) -> str:
        """The server's Prometheus metrics, as text (``GET /metrics``)."""
        return self._send("GET", "/metrics").text

    def model(self) -> dict[str, Any]:
        """The default model: id, variant, config and provenance (``GET /v1/model``)."""
        return self._send("GET", "/v1/model").json()

    def models(self) -> list[dict[str, Any]]:
        """Every model the server serves (``GET /v1/models``): its ``name`` (what ``model=``
        takes), path, whether it is the ``default``, and what its manifest says."""
        return self._send("GET", "/v1/models").json()["models"]

    def reload_models(self) -> dict[str, Any]:
        """Has the server load the bundles added to its ``--models`` folder
        (``POST /v1/models/reload``): ``{"loaded": [...], "skipped": [{"name", "path", "reason"}]}``."""
        return self._send("POST", "/v1/models/reload").json()

    def limits(self) -> Limits:
        """The server's request limits (``GET /v1/limits``), asked once."""
        if self._limits is None:
            body = self._send("GET", "/v1/limits").json()
            self._limits = Limits(**{k: int(body[k]) for k in Limits.__dataclass_fields__})
        return self._limits

    # -- one-shot renders

    def render(
        self,
        images: Sequence[ImageLike],
        cameras: Sequence[CameraLike],
        target: CameraLike,
        near: float,
        far: float,
        background: Sequence[float] | None = None,
        outputs: Outputs = ALL_OUTPUTS,
        sampling: str | None = None,
        model: str | None = None,
    ) -> Rendering:
        """One view from source ``images`` (arrays, PIL images, PNG/JPEG bytes or files) with
        their ``cameras`` (``POST /v1/render``), by ``model`` (default: the server's)."""
        document = self._scene_document(cameras, near, far, background, model)
        document.update(self._target_document(target, outputs, sampling))
        response = self._send("POST", "/v1/render", files=self._parts(document, images))
        return self._rendering(response)

    # -- scenes

    def upload_scene(
        self,
        images: Sequence[ImageLike],
        cameras: Sequence[CameraLike],
        near: float,
        far: float,
        background: Sequence[float] | None = None,
        scene_id: str | None = None,
        model: str | None = None,
    ) -> Scene:
        """Encodes the sources once (``PUT /v1/scenes/{id}``); views of it cost only the renderer.
        The id is ``scene_id``, or derived from what is uploaded (the same upload, the same id).
        The scene belongs to ``model`` (default: the server's), which renders its views."""
        document = self._scene_document(cameras, near, far, background, model)
        parts = self._parts(document, images)
        if scene_id is None:
            digest = hashlib.sha256()
            for _, (_, data, _) in parts:
                digest.update(len(data).to_bytes(8, "little") + data)
            scene_id = f"py-{digest.hexdigest()[:32]}"

        scene = Scene(scene_id, [s["camera"] for s in document["sources"]], near, far)

        def upload() -> str:
            response = self._send("PUT", f"/v1/scenes/{scene_id}", files=parts)
            scene.timings = server_timing(response.headers.get("server-timing", ""))
            body = response.json()
            scene.model = body.get("model")
            return body["scene_id"]

        upload()
        scene.upload = upload
        return scene

    def upload_capture(
        self,
        folder: str | Path,
        downscale: int | None = None,
        near: float | None = None,
        far: float | None = None,
        ignore_distortion: bool = False,
        model: str | None = None,
    ) -> Scene:
        """A capture folder as its tools leave it (COLMAP, nerfstudio, Blender, LLFF, DTU) as a
        scene (``POST /v1/captures``): the server reads its cameras. What is sent is the server's
        plan (``POST /v1/captures/plan``): the capture's files, of the image sets ``images/``,
        ``images_N/`` the one ``downscale`` names or else the largest within the server's source
        limit, and images beyond that limit resized here first to the size it says."""
        limits = self.limits()
        planned = captures.plan(folder, self._plan_capture, downscale)
        chosen = captures.collect(folder, planned)
        if chosen.bytes > limits.max_capture_bytes:
            raise CaptureError(
                f"{folder}: {chosen.bytes / 2**20:.1f} MiB to send, more than the server takes "
                f"({limits.max_capture_bytes / 2**20:.1f} MiB, its --max-capture-bytes): pass downscale=N"
            )
        query = {"downscale": downscale, "near": near, "far": far, "model": model}
        params = {k: v for k, v in query.items() if v is not None}
        if ignore_distortion:
            params["ignore_distortion"] = "true"
        parts = [("file", (name, data, "application/octet-stream")) for name, data in chosen.files]
        scene = Scene("", [], 0.0, 0.0, notes=chosen.notes)

        def upload() -> str:
            response = self._send("POST", "/v1/captures", files=parts, params=params)
            body, scene.timings = response.json(), server_timing(response.headers.get("server-timing", ""))
            scene.id, scene.cameras, scene.near, scene.far = (
                body["scene_id"],
                body["cameras"],
                body["near"],
                body["far"],
            )
            scene.names, scene.format = body.get("names", []), body.get("format")
            scene.image_set, scene.warnings = body.get("image_set"), body.get("warnings", [])
            scene.model = body.get("model")
            return scene.id

        upload()
        scene.upload = upload
        return scene

    def _plan_capture(self, listing: dict[str, Any]) -> dict[str, Any]:
        """``POST /v1/captures/plan``: what to send of a capture folder, from its listing."""
        return self._send("POST", "/v1/captures/plan", json=listing).json()

    def render_scene(
        self,
        scene: Scene | str,
        target: CameraLike,
        outputs: Outputs = ALL_OUTPUTS,
        sources: Sequence[int] | None = None,
        sampling: str | None = None,
        model: str | None = None,
    ) -> Rendering:
        """A view of a scene (``POST /v1/scenes/{id}/render``); ``sources`` pins its three source
        views. The scene's model renders it; ``model`` naming another is refused (409
        ``model_mismatch``). A :class:`Scene` the server lost is uploaded again once."""
        document = self._target_document(target, outputs, sampling)
        if model is not None:
            document["model"] = model
        if sources is not None:
            document["sources"] = [int(i) for i in sources]
        scene_id = scene.id if isinstance(scene, Scene) else scene
        try:
            return self._rendering(self._send("POST", f"/v1/scenes/{scene_id}/render", json=document))
        except SceneNotFound as gone:
            if not (isinstance(scene, Scene) and scene.upload and gone.hint == "reupload"):
                raise
            scene.id = scene.upload()
            return self._rendering(self._send("POST", f"/v1/scenes/{scene.id}/render", json=document))

    def delete_scene(self, scene: Scene | str) -> None:
        self._send("DELETE", f"/v1/scenes/{scene.id if isinstance(scene, Scene) else scene}")

    # -- the wire

    @staticmethod
    def _scene_document(cameras, near, far, background, model: str | None = None) -> dict[str, Any]:
        document: dict[str, Any] = {
            "sources": [{"camera": camera_json(c)} for c in cameras],
            "near": float(near),
            "far": float(far),
        }
        if background is not None:
            document["background"] = [float(b) for b in background]
        # Only when named: a document without it is the one earlier clients sent (the same id).
        if model is not None:
            document["model"] = model
        return document

    @staticmethod
    def _target_document(target: CameraLike, outputs: Outputs, sampling: str | None) -> dict[str, Any]:
        document: dict[str, Any] = {"target": camera_json(target), "outputs": list(outputs)}
        if sampling is not None:
            document["sampling"] = sampling
        return document

    @staticmethod
    def _parts(document: dict[str, Any], images: Sequence[ImageLike]) -> list:
        parts: list = [("request", ("request.json", json.dumps(document).encode(), "application/json"))]
        for i, image in enumerate(images):
            data, content_type = encoded(image)
            parts.append((f"source_{i}", (f"source_{i}", data, content_type)))
        return parts

    def _send(self, method: str, path: str, **kwargs) -> requests.Response:
        """One call, 503/429 waited out (``Retry-After`` seconds, at most ``max_retries`` times);
        any other error status raises the server's error, typed."""
        for attempt in range(self.max_retries + 1):
            try:
                response = self.session.request(method, self.url + path, timeout=self.timeout, **kwargs)
            except requests.ConnectionError as e:
                raise ConnectionFailed(f"cannot reach the server at {self.url}{path}: {e}") from e
            if response.ok:
                return response
            retry_after = _seconds(response.headers.get("retry-after"))
            if response.status_code in (429, 503) and attempt < self.max_retries:
                time.sleep(retry_after if retry_after is not None else 1.0)
                continue
            raise server_error(
                response.status_code, response.content, response.headers.get("x-request-id"), retry_after
            )
        raise AssertionError("unreachable")

    @staticmethod
    def _rendering(response: requests.Response) -> Rendering:
        body = response.json()
        h, w = body["height"], body["width"]
        header = response.headers.get("x-scnerf-sources")
        sources = [int(i) for i in header.split(",")] if header else body.get("sources")
        return Rendering(
            rgb=decode_rgb(body["rgb"]["data"]) if "rgb" in body else None,
            depth=decode_floats(body["depth"]["data"], h, w) if "depth" in body else None,
            opacity=decode_floats(body["opacity"]["data"], h, w) if "opacity" in body else None,
            timings=body.get("timings_ms", {}),
            model_id=body.get("model_id", ""),
            sources=sources,
            sampling=body.get("sampling"),
            model=body.get("model"),
            samples_per_ray=body.get("samples_per_ray"),
        )


def server_timing(header: str) -> dict[str, float]:
    """``encoder;dur=812.5, volume;dur=90`` as ``{"encoder": 812.5, "volume": 90.0}``."""
    found = (re.match(r"\s*([\w-]+)\s*;\s*dur=([\d.]+)", item) for item in header.split(","))
    return {m.group(1): float(m.group(2)) for m in found if m}


def _seconds(value: str | None) -> float | None:
    try:
        return float(value) if value is not None else None
    except ValueError:
        return None
