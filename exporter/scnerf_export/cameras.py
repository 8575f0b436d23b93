"""Cameras in the canonical form (OpenCV axes, world-to-camera) and the rays the server sends.

The centre of pixel (u, v) is at image coordinates (u, v). Ray and projection maths runs in
float64 and is cast to float32 once, exactly as the Rust server does, so both feed the graphs
bit-identical inputs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass
class Camera:
    K: np.ndarray  # (3,3) intrinsics
    w2c: np.ndarray  # (4,4) world-to-camera, OpenCV axes (x right, y down, z forward)
    width: int
    height: int

    @property
    def c2w(self) -> np.ndarray:
        return np.linalg.inv(self.w2c)

    @property
    def rotation(self) -> np.ndarray:
        """World-to-camera rotation (3, 3)."""
        return self.w2c[:3, :3]

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates (3,)."""
        return -self.w2c[:3, :3].T @ self.w2c[:3, 3]

    @property
    def forward(self) -> np.ndarray:
        """Unit optical axis in world coordinates."""
        return self.w2c[2, :3].copy()

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World points (N, 3) -> pixel coordinates (N, 2) and z-depth (N,)."""
        cam = points @ self.w2c[:3, :3].T + self.w2c[:3, 3]
        z = cam[:, 2]
        uv = (cam[:, :2] / z[:, None]) * np.diag(self.K)[:2] + self.K[:2, 2]
        return uv, z

    def unproject(self, uv: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """Pixel coordinates (N, 2) with z-depths (N,) -> world points (N, 3)."""
        fx, fy, cx, cy = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]
        cam = np.stack([(uv[:, 0] - cx) / fx, (uv[:, 1] - cy) / fy, np.ones(len(uv))], axis=-1)
        cam = cam * depth[:, None]
        return (cam - self.w2c[:3, 3]) @ self.w2c[:3, :3]

    @classmethod
    def from_pose(cls, K, matrix, width: int, height: int, kind: str = "world_to_camera",
                  axes: str = "opencv") -> "Camera":
        """Build a canonical camera from any of the API's pose conventions."""
        matrix = np.asarray(matrix, dtype=np.float64)
        c2w = matrix if kind == "camera_to_world" else np.linalg.inv(matrix)
        if axes == "opengl":
            c2w = c2w @ OPENGL_TO_OPENCV
        return cls(np.asarray(K, dtype=np.float64), np.linalg.inv(c2w), int(width), int(height))

    def scaled(self, factor: float) -> "Camera":
        """The camera of the image resized by ``factor`` (pixel centres stay at integers)."""
        K = self.K.copy()
        K[0, 0] *= factor
        K[1, 1] *= factor
        K[0, 2] = (K[0, 2] + 0.5) * factor - 0.5
        K[1, 2] = (K[1, 2] + 0.5) * factor - 0.5
        return Camera(K, self.w2c.copy(), round(self.width * factor), round(self.height * factor))


def target_rays(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Rays through every pixel centre, row-major: origins (HW,3), directions (HW,3) float32.

    Directions are R_c2w [(u-cx)/fx, (v-cy)/fy, 1]: the sample parameter is the target z-depth.
    """
    K, c2w = camera.K, camera.c2w
    v, u = np.meshgrid(np.arange(camera.height, dtype=np.float64),
                       np.arange(camera.width, dtype=np.float64), indexing="ij")
    cam_dirs = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)
    directions = cam_dirs.reshape(-1, 3) @ c2w[:3, :3].T
    origins = np.broadcast_to(c2w[:3, 3], directions.shape)
    return origins.astype(np.float32), directions.astype(np.float32)


def intrinsics_4x4(K: np.ndarray) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = K
    return m


def feature_projections(cameras: list[Camera]) -> np.ndarray:
    """(V,4,4) float32: diag(1/4,1/4,1,1) [[K,0],[0,1]] w2c, the cost volume's projections."""
    quarter = np.diag([0.25, 0.25, 1.0, 1.0])
    return np.stack([quarter @ intrinsics_4x4(c.K) @ c.w2c for c in cameras]).astype(np.float32)


def stack_intrinsics(cameras: list[Camera]) -> np.ndarray:
    return np.stack([c.K for c in cameras]).astype(np.float32)


def stack_extrinsics(cameras: list[Camera]) -> np.ndarray:
    return np.stack([c.w2c for c in cameras]).astype(np.float32)


def depth_planes(near: float, far: float, count: int) -> np.ndarray:
    steps = np.linspace(0.0, 1.0, count, dtype=np.float64)
    return (near * (1.0 - steps) + far * steps).astype(np.float32)


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """World-to-camera matrix (4, 4) of a camera at ``eye`` looking at ``target`` (OpenCV axes):
    x = forward x up (right), y = forward x right (down), so det(R) = +1."""
    eye = np.asarray(eye, dtype=np.float64)
    forward = np.asarray(target, dtype=np.float64) - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, np.asarray(up, dtype=np.float64))
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    w2c = np.eye(4)
    w2c[:3, :3] = np.stack([right, down, forward])
    w2c[:3, 3] = -w2c[:3, :3] @ eye
    return w2c


def pinhole(focal: float, width: int, height: int) -> np.ndarray:
    return np.array([[focal, 0.0, (width - 1) / 2.0], [0.0, focal, (height - 1) / 2.0], [0.0, 0.0, 1.0]])


def rank_sources(target: Camera, candidates: list[Camera]) -> list[int]:
    """Source selection, MVSNeRF's rule: candidates ordered by the distance of their camera centre
    to the target's, nearest first (the first becomes the volume's reference view). Ties go to the
    lower index, so the choice is deterministic; a candidate whose optical axis faces away from the
    target's (angle >= 90 degrees) sees the other side of the scene and is left out."""
    distance = np.array([np.linalg.norm(c.center - target.center) for c in candidates])
    facing = np.array([float(c.forward @ target.forward) > 0.0 for c in candidates])
    order = np.lexsort((np.arange(len(candidates)), distance))
    return [int(i) for i in order if facing[i]]
