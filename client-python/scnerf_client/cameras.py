"""Cameras in the API's form: pinhole intrinsics (the centre of pixel (u, v) at image coordinates
(u, v)) and a 4x4 pose, world-to-camera or camera-to-world, in OpenCV or OpenGL axes; the server
converts them to its canonical OpenCV world-to-camera form."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

PoseKind = Literal["world_to_camera", "camera_to_world"]
Axes = Literal["opencv", "opengl"]


@dataclass
class Camera:
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    pose: np.ndarray = field(default_factory=lambda: np.eye(4))
    kind: PoseKind = "world_to_camera"
    axes: Axes = "opencv"

    def __repr__(self) -> str:
        m = np.asarray(self.pose, float)
        centre = m[:3, 3] if self.kind == "camera_to_world" else -m[:3, :3].T @ m[:3, 3]
        return (
            f"Camera({self.width}x{self.height}, f {self.fx:g},{self.fy:g}, c {self.cx:g},{self.cy:g}, "
            f"centre ({centre[0]:.3g}, {centre[1]:.3g}, {centre[2]:.3g}), {self.kind} {self.axes})"
        )

    def to_json(self) -> dict[str, Any]:
        """The API's JSON camera."""
        return {
            "width": int(self.width),
            "height": int(self.height),
            "intrinsics": {"fx": float(self.fx), "fy": float(self.fy), "cx": float(self.cx), "cy": float(self.cy)},
            "pose": {"matrix": np.asarray(self.pose, float).tolist(), "kind": self.kind, "axes": self.axes},
        }

    @classmethod
    def from_json(cls, camera: dict[str, Any]) -> Camera:
        """A camera in the API's JSON form (``intrinsics`` as {fx, fy, cx, cy} or 3x3, or ``K``)."""
        k = camera.get("intrinsics", camera.get("K"))
        if isinstance(k, dict):
            fx, fy, cx, cy = k["fx"], k["fy"], k["cx"], k["cy"]
        else:
            fx, fy, cx, cy = k[0][0], k[1][1], k[0][2], k[1][2]
        pose = camera["pose"]
        return cls(
            camera["width"],
            camera["height"],
            fx,
            fy,
            cx,
            cy,
            np.asarray(pose["matrix"], float),
            pose["kind"],
            pose["axes"],
        )

    def resized(self, width: int, height: int) -> Camera:
        """The same view at another size: f' = f s, c' = (c + 0.5) s - 0.5 (pixel centres stay at integers)."""
        sx, sy = width / self.width, height / self.height
        return Camera(
            width,
            height,
            self.fx * sx,
            self.fy * sy,
            (self.cx + 0.5) * sx - 0.5,
            (self.cy + 0.5) * sy - 0.5,
            self.pose,
            self.kind,
            self.axes,
        )


CameraLike = Camera | dict[str, Any]


def camera_json(camera: CameraLike) -> dict[str, Any]:
    return camera.to_json() if isinstance(camera, Camera) else camera
