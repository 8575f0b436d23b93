"""Python client of scnerf-serve (SC-NeRF novel-view rendering): ``Client(url, token)`` with
``model()``, ``models()``, ``limits()``, ``render(...)``, ``upload_scene(...)``, ``upload_capture(folder)`` and
``render_scene(scene, target)``; renders come back as numpy arrays."""

from .cameras import Camera
from .client import Client, Limits, Rendering, Scene
from .errors import (
    CaptureError,
    ConnectionFailed,
    InvalidRequest,
    ModelMismatch,
    ModelNotFound,
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
    "ModelMismatch",
    "ModelNotFound",
    "Overloaded",
    "Rendering",
    "Scene",
    "SceneNotFound",
    "ScnerfError",
    "ServerError",
    "Unauthorized",
]
