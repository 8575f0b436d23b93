"""Analytic primitives and their ray intersections, vectorised over all rays of an image.

Each primitive has a frame (centre + rotation whose columns are its local axes in world space), so
boxes and cylinders can be oriented and textures stick to the object.  ``intersect(o, d)`` takes one
ray origin (3,) or per-ray origins (N, 3) and directions (N, 3) that are *not* normalised, and returns
the smallest ray parameter t > EPS (``inf`` for a miss); with the renderer's directions (camera-frame
z = 1) that t is the z-depth.  All maths is float64 so depths are exact to ~1e-12.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .textures import Material

EPS = 1e-6


def _rows(x: np.ndarray) -> np.ndarray:
    """Broadcastable (N, 3) view of one point (3,) or many (N, 3)."""
    return x[None, :] if x.ndim == 1 else x


def rotation_from_euler(yaw: float, pitch: float = 0.0, roll: float = 0.0) -> np.ndarray:
    """Rotation matrix (columns = local axes in world) from z-y-x Euler angles in radians."""
    cz, sz = np.cos(yaw), np.sin(yaw)
    cy, sy = np.cos(pitch), np.sin(pitch)
    cx, sx = np.cos(roll), np.sin(roll)
    rz = np.array([[cz, -sz, 0.0], [sz, cz, 0.0], [0.0, 0.0, 1.0]])
    ry = np.array([[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]])
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cx, -sx], [0.0, sx, cx]])
    return rz @ ry @ rx


@dataclass
class Primitive:
    """Common frame handling; subclasses implement ``_intersect_local`` and ``_normal_local``."""

    center: np.ndarray
    material: Material
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))

    @property
    def bound(self) -> float:
        """Radius of a sphere around ``center`` that contains the primitive (inf if unbounded)."""
        return np.inf

    def to_local(self, p: np.ndarray) -> np.ndarray:
        return (_rows(p) - self.center) @ self.rotation

    def intersect(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        return self._intersect_local(self.to_local(o), d @ self.rotation)

    def normal(self, p: np.ndarray) -> np.ndarray:
        """Unit outward normals (N, 3) in world space at surface points p (N, 3)."""
        return self._normal_local(self.to_local(p)) @ self.rotation.T

    def _intersect_local(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:  # pragma: no cover
        raise NotImplementedError

    def _normal_local(self, p: np.ndarray) -> np.ndarray:  # pragma: no cover
        raise NotImplementedError


def _nearest_positive(*candidates: np.ndarray) -> np.ndarray:
    t = np.full(np.broadcast_shapes(*(c.shape for c in candidates)), np.inf)
    for c in candidates:
        t = np.where((c > EPS) & (c < t), c, t)
    return t


@dataclass
class Sphere(Primitive):
    radius: float = 1.0

    @property
    def bound(self) -> float:
        return self.radius

    def _intersect_local(self, o, d):
        a = np.einsum("ij,ij->i", d, d)
        b = np.einsum("ij,ij->i", np.broadcast_to(o, d.shape), d)
        c = np.einsum("ij,ij->i", o, o) - self.radius**2
        disc = b * b - a * c
        sq = np.sqrt(np.maximum(disc, 0.0))
        # the numerically stable pair of roots (no cancellation for the near root)
        q = -(b + np.copysign(sq, b))
        with np.errstate(divide="ignore", invalid="ignore"):
            t0, t1 = q / a, c / q
        t = _nearest_positive(np.where(np.isfinite(t0), t0, np.inf), np.where(np.isfinite(t1), t1, np.inf))
        return np.where(disc >= 0.0, t, np.inf)

    def _normal_local(self, p):
        return p / np.linalg.norm(p, axis=-1, keepdims=True)


@dataclass
class Box(Primitive):
    half: np.ndarray = field(default_factory=lambda: np.ones(3))

    @property
    def bound(self) -> float:
        return float(np.linalg.norm(self.half))

    def _intersect_local(self, o, d):
        safe = np.where(np.abs(d) < 1e-15, np.copysign(1e-15, d), d)
        inv = 1.0 / safe
        t1 = (-self.half - o) * inv
        t2 = (self.half - o) * inv
        lo, hi = np.minimum(t1, t2), np.maximum(t1, t2)
        # explicit per-axis max/min: numpy's reductions over a length-3 last axis are slow
        tmin = np.maximum(np.maximum(lo[:, 0], lo[:, 1]), lo[:, 2])
        tmax = np.minimum(np.minimum(hi[:, 0], hi[:, 1]), hi[:, 2])
        hit = (tmax >= tmin) & (tmax > EPS)
        return np.where(hit, np.where(tmin > EPS, tmin, tmax), np.inf)

    def _normal_local(self, p):
        q = p / self.half
        axis = np.abs(q).argmax(axis=-1)
        n = np.zeros_like(p)
        n[np.arange(len(p)), axis] = np.sign(q[np.arange(len(p)), axis])
        return n


@dataclass
class Cylinder(Primitive):
    """Capped cylinder along the local z axis."""

    radius: float = 0.5
    half_height: float = 0.5

    @property
    def bound(self) -> float:
        return float(np.hypot(self.radius, self.half_height))

    def _intersect_local(self, o, d):
        o = np.broadcast_to(o, d.shape)
        ox, oy, oz = o[:, 0], o[:, 1], o[:, 2]
        dx, dy, dz = d[:, 0], d[:, 1], d[:, 2]
        a = dx * dx + dy * dy
        b = ox * dx + oy * dy
        c = ox * ox + oy * oy - self.radius**2
        disc = b * b - a * c
        sq = np.sqrt(np.maximum(disc, 0.0))
        with np.errstate(divide="ignore", invalid="ignore"):
            side0 = (-b - sq) / a
            side1 = (-b + sq) / a
            cap0 = (-self.half_height - oz) / dz
            cap1 = (self.half_height - oz) / dz

        def on_side(t):
            ok = (disc >= 0.0) & (a > 1e-18) & np.isfinite(t) & (np.abs(oz + t * dz) <= self.half_height)
            return np.where(ok, t, np.inf)

        def on_cap(t):
            ok = np.isfinite(t) & ((ox + t * dx) ** 2 + (oy + t * dy) ** 2 <= self.radius**2)
            return np.where(ok, t, np.inf)

        return _nearest_positive(on_side(side0), on_side(side1), on_cap(cap0), on_cap(cap1))

    def _normal_local(self, p):
        rad = np.hypot(p[:, 0], p[:, 1])
        cap = np.abs(p[:, 2]) / self.half_height > rad / self.radius
        side = np.stack([p[:, 0], p[:, 1], np.zeros(len(p))], axis=-1) / np.maximum(rad, 1e-12)[:, None]
        capn = np.stack([np.zeros(len(p)), np.zeros(len(p)), np.sign(p[:, 2])], axis=-1)
        return np.where(cap[:, None], capn, side)


@dataclass
class Plane(Primitive):
    """The local z = 0 plane, optionally limited to |x| <= half[0], |y| <= half[1] (inf = unbounded).
    Two-sided: the renderer turns normals towards the viewer."""

    half: tuple[float, float] = (np.inf, np.inf)

    @property
    def bound(self) -> float:
        return float(np.hypot(*self.half))

    def _intersect_local(self, o, d):
        o = np.broadcast_to(o, d.shape)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = -o[:, 2] / d[:, 2]
        x = o[:, 0] + t * d[:, 0]
        y = o[:, 1] + t * d[:, 1]
        ok = np.isfinite(t) & (t > EPS) & (np.abs(x) <= self.half[0]) & (np.abs(y) <= self.half[1])
        return np.where(ok, t, np.inf)

    def _normal_local(self, p):
        n = np.zeros_like(p)
        n[:, 2] = 1.0
        return n


@dataclass
class SkyDome(Sphere):
    """A large emissive sphere around the scene: the outdoor sky/background.

    A real surface (rather than colour by direction at infinity) keeps depth exact and the images
    exactly multi-view consistent; its radius is chosen so that it lies inside every view's far plane.
    """

    zenith: np.ndarray = field(default_factory=lambda: np.array([0.3, 0.5, 0.85]))
    horizon: np.ndarray = field(default_factory=lambda: np.array([0.75, 0.82, 0.9]))
    cloud_seed: int = 0
    cloud_amount: float = 0.0

    @property
    def bound(self) -> float:
        return np.inf  # the camera is inside: culling would gain nothing
