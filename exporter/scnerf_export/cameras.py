"""Cameras in the canonical form (OpenCV axes, world-to-camera), the conversions from every other
pose convention, the camera JSON of the API, and the rays the server sends. The one home of these
conventions: the data loaders, the fixtures, the benchmark and the tests import them from here.

The centre of pixel (u, v) is at image coordinates (u, v). Ray and projection maths runs in
float64 and is cast to float32 once, exactly as the Rust server does, so both feed the graphs
bit-identical inputs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# Flips y and z: OpenGL camera axes (x right, y up, z back) <-> OpenCV's (x right, y down, z forward).
# It is its own inverse.
OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])


def invert_rigid(m: np.ndarray) -> np.ndarray:
    """Inverse of a 4x4 [R|t] matrix, exact for rotations (falls back to a general inverse): the
    data loaders' inverse. Requests are decoded with the general inverse, as the server does."""
    r = m[:3, :3]
    if np.allclose(r @ r.T, np.eye(3), atol=1e-6) and np.allclose(m[3], [0, 0, 0, 1]):
        out = np.eye(4)
        out[:3, :3] = r.T
        out[:3, 3] = -r.T @ m[:3, 3]
        return out
    return np.linalg.inv(m)


def canonical_w2c(matrix, kind: str = "world_to_camera", axes: str = "opencv", invert=np.linalg.inv) -> np.ndarray:
    """A pose in any of the API's conventions (``kind``: world_to_camera | camera_to_world, ``axes``:
    opencv | opengl; 4x4 or 3x4) -> world-to-camera in OpenCV axes (4, 4).

    ``invert`` is the general inverse by default, the arithmetic of the server's decoding
    (capture/src/camera.rs: canonical_w2c, a general inverse like numpy.linalg.inv), so that both feed
    the graphs the same cameras; the data loaders pass :func:`invert_rigid`."""
    m = np.asarray(matrix, dtype=np.float64)
    if m.shape == (3, 4):
        m = np.vstack([m, [0.0, 0.0, 0.0, 1.0]])
    if m.shape != (4, 4):
        raise ValueError(f"expected a 4x4 (or 3x4) pose matrix, got shape {m.shape}")
    c2w = m if kind == "camera_to_world" else invert(m)
    if axes == "opengl":
        c2w = c2w @ OPENGL_TO_OPENCV
    return invert(c2w)


def opengl_c2w_to_opencv_w2c(c2w_gl: np.ndarray) -> np.ndarray:
    """Camera-to-world in OpenGL axes (Blender, nerfstudio) -> world-to-camera in OpenCV axes."""
    return canonical_w2c(c2w_gl, "camera_to_world", "opengl", invert_rigid)


def opencv_w2c_to_opengl_c2w(w2c_cv: np.ndarray, invert=invert_rigid) -> np.ndarray:
    """Inverse of :func:`opengl_c2w_to_opencv_w2c`."""
    return invert(np.asarray(w2c_cv, dtype=np.float64)) @ OPENGL_TO_OPENCV


def scaled_size(width: int, height: int, factor: float) -> tuple[int, int]:
    """The size of an image resized by ``factor``, at least one pixel."""
    return max(1, int(round(width * factor))), max(1, int(round(height * factor)))


@dataclass
class Camera:
    K: np.ndarray  # (3,3) intrinsics
    w2c: np.ndarray  # (4,4) world-to-camera, OpenCV axes (x right, y down, z forward)
    width: int
    height: int

    @property
    def c2w(self) -> np.ndarray:
        """Camera-to-world by the general inverse, as the server computes it: the rays match its rays."""
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
    def from_pose(
        cls, K, matrix, width: int, height: int, kind: str = "world_to_camera", axes: str = "opencv"
    ) -> "Camera":
        """Build a canonical camera from any of the API's pose conventions."""
        return cls(np.asarray(K, dtype=np.float64), canonical_w2c(matrix, kind, axes), int(width), int(height))

    def resized(self, width: int, height: int) -> "Camera":
        """The camera of the same view resampled to width x height: for the exact ratio s of the new
        to the old size along an axis, f' = f s and c' = (c + 0.5) s - 0.5, so pixel centres stay
        at integers."""
        sx, sy = width / self.width, height / self.height
        K = np.asarray(self.K, dtype=np.float64).copy()
        K[0, 0] *= sx
        K[0, 1] *= sx
        K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
        K[1, 1] *= sy
        K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
        return Camera(K, np.asarray(self.w2c, dtype=np.float64).copy(), int(width), int(height))

    def scaled(self, factor: float) -> "Camera":
        """The camera of the image resized by ``factor`` (:meth:`resized`)."""
        return self.resized(*scaled_size(self.width, self.height, factor))


def target_rays(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Rays through every pixel centre, row-major: origins (HW,3), directions (HW,3) float32.

    Directions are R_c2w [(u-cx)/fx, (v-cy)/fy, 1]: the sample parameter is the target z-depth.
    """
    K, c2w = camera.K, camera.c2w
    v, u = np.meshgrid(
        np.arange(camera.height, dtype=np.float64), np.arange(camera.width, dtype=np.float64), indexing="ij"
    )
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
    """K of square pixels with the principal point at the image centre, ((W - 1) / 2, (H - 1) / 2)."""
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


def camera_json(camera: Camera, pose: str = "opencv_w2c") -> dict:
    """A camera as the API's JSON object: the pose in the canonical form (``opencv_w2c``) or as
    OpenGL camera-to-world (``opengl_c2w``); both must decode to the same camera."""
    K = camera.K
    if pose == "opengl_c2w":
        matrix, kind, axes = opencv_w2c_to_opengl_c2w(camera.w2c, np.linalg.inv), "camera_to_world", "opengl"
    else:
        matrix, kind, axes = camera.w2c, "world_to_camera", "opencv"
    return {
        "width": int(camera.width),
        "height": int(camera.height),
        "intrinsics": {"fx": float(K[0, 0]), "fy": float(K[1, 1]), "cx": float(K[0, 2]), "cy": float(K[1, 2])},
        "pose": {"matrix": matrix.tolist(), "kind": kind, "axes": axes},
    }


def intrinsics_from_json(camera: dict) -> np.ndarray:
    """K (3, 3) of an API camera object's ``intrinsics: {fx, fy, cx, cy}``."""
    i = camera["intrinsics"]
    return np.array([[i["fx"], 0, i["cx"]], [0, i["fy"], i["cy"]], [0, 0, 1]], dtype=np.float64)


def camera_from_json(camera: dict) -> Camera:
    """The canonical camera of an API camera object, decoded as the server decodes it."""
    pose = camera["pose"]
    return Camera.from_pose(
        intrinsics_from_json(camera), pose["matrix"], camera["width"], camera["height"], pose["kind"], pose["axes"]
    )
