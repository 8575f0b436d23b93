"""Python client of scnerf-serve (SC-NeRF novel-view rendering): ``Client(url, token)`` with
``model()``, ``limits()``, ``render(...)``, ``upload_scene(...)``, ``upload_capture(folder)`` and
``render_scene(scene, target)``; renders come back as numpy arrays."""

from .cameras import Camera
from .client import Client, Limits, Rendering, Scene
from .errors import (
    CaptureError,
    ConnectionFailed,
    InvalidRequest,
    Overloaded,
    SceneNotFound,
    ScnerfError,
    ServerError,
    Unauthorized,
)

__all__ = [
    "Camera",
    "CaptureError",
    "Client",
    "ConnectionFailed",
    "InvalidRequest",
    "Limits",
    "Overloaded",
    "Rendering",
    "Scene",
    "SceneNotFound",
    "ScnerfError",
    "ServerError",
    "Unauthorized",
]
