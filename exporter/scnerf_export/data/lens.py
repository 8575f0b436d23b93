"""Lens distortion in the Python readers: a distorted photo is resampled to the pinhole camera the
Rust readers send it as (capture/src/undistort.rs, its default fit): at the photo's size, the
largest rectangle of valid pixels (the undistorted border, 33 points a side, as the Rust rule
samples it), sampled bilinearly, pixels no photo pixel reaches filled with the background.
OpenCV's models, by OpenCV's own functions:
- perspective, coefficients in OpenCV's order ``k1 k2 p1 p2 k3 [k4 k5 k6]`` (COLMAP's OPENCV and
  FULL_OPENCV write them so);
- fisheye (``cv2.fisheye``), ``k1 k2 k3 k4`` on the angle from the axis.

Both act on normalised image coordinates: coefficients do not change when the image is resized.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

BORDER_SAMPLES = 33  # capture/src/undistort.rs
_CONVERGED = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)
# A border point whose undistorted position distorts back farther than this from it has none.
_INVERTED_PX = 1e-6


@dataclass(frozen=True)
class Distortion:
    """A lens's distortion in OpenCV's terms."""

    coefficients: np.ndarray
    fisheye: bool = False

    def undistort_points(self, pixels: np.ndarray, K: np.ndarray) -> np.ndarray:
        """Normalised undistorted coordinates (N,2) of photo pixels (N,2); ValueError where the
        model maps no point there."""
        points = pixels.reshape(-1, 1, 2).astype(np.float64)
        if self.fisheye:
            normalised = cv2.fisheye.undistortPoints(points, K, self.coefficients, criteria=_CONVERGED)
            back = cv2.fisheye.distortPoints(normalised, K, self.coefficients)
        else:
            normalised = cv2.undistortPoints(points, K, self.coefficients, None, None, None, _CONVERGED)
            rays = np.concatenate([normalised.reshape(-1, 2), np.ones((len(pixels), 1))], axis=1)
            back, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), K, self.coefficients)
        if not np.abs(back.reshape(-1, 2) - pixels).max() <= _INVERTED_PX:
            raise ValueError("its lens distortion cannot be inverted over the whole image: check the coefficients")
        return normalised.reshape(-1, 2)

    def maps(self, K: np.ndarray, pinhole: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        """Where in the photo each pixel of the ``pinhole`` image comes from: x and y (H,W)."""
        size, maptype = (int(width), int(height)), cv2.CV_32FC1
        if self.fisheye:
            return cv2.fisheye.initUndistortRectifyMap(K, self.coefficients, np.eye(3), pinhole, size, maptype)
        return cv2.initUndistortRectifyMap(K, self.coefficients, None, pinhole, size, maptype)


def perspective(k1=0.0, k2=0.0, p1=0.0, p2=0.0, k3=0.0, k4=0.0, k5=0.0, k6=0.0) -> Distortion | None:
    """OpenCV's perspective model (the rational k4..k6 only when one is set); None without distortion."""
    rational = (k4, k5, k6) if any((k4, k5, k6)) else ()
    return _distortion([k1, k2, p1, p2, k3, *rational], fisheye=False)


def fisheye(k1=0.0, k2=0.0, k3=0.0, k4=0.0) -> Distortion | None:
    """OpenCV's fisheye model; None without distortion."""
    return _distortion([k1, k2, k3, k4], fisheye=True)


def _distortion(coefficients: list[float], fisheye: bool) -> Distortion | None:
    return Distortion(np.array(coefficients, dtype=np.float64), fisheye) if any(coefficients) else None


def pinhole_for(K: np.ndarray, distortion: Distortion, width: int, height: int) -> np.ndarray:
    """The pinhole intrinsics, for an image of the same size, whose every pixel sees the photo:
    the largest rectangle inside the undistorted border (capture/src/undistort.rs ``pinhole_for``)."""
    w, h = width - 1.0, height - 1.0
    t = np.linspace(0.0, 1.0, BORDER_SAMPLES)

    def side(u0, v0, u1, v1):
        return distortion.undistort_points(np.stack([u0 + (u1 - u0) * t, v0 + (v1 - v0) * t], axis=1), K)

    left, right, top, bottom = side(0, 0, 0, h), side(w, 0, w, h), side(0, 0, w, 0), side(0, h, w, h)
    x0, x1, y0, y1 = left[:, 0].max(), right[:, 0].min(), top[:, 1].max(), bottom[:, 1].min()
    if not (x1 > x0 and y1 > y0):
        raise ValueError("its lens distortion leaves no rectangle of valid pixels: check the coefficients")
    fx, fy = w / (x1 - x0), h / (y1 - y0)
    return np.array([[fx, 0.0, -fx * x0], [0.0, fy, -fy * y0], [0.0, 0.0, 1.0]])


def undistort(image: np.ndarray, K: np.ndarray, distortion: Distortion, background) -> tuple[np.ndarray, np.ndarray]:
    """``image`` (H,W,3 float32) resampled to the pinhole camera ``pinhole_for`` gives: the image
    and that camera's intrinsics."""
    height, width = image.shape[:2]
    pinhole = pinhole_for(K, distortion, width, height)
    map_x, map_y = distortion.maps(K, pinhole, width, height)
    fill = tuple(float(c) for c in background)
    out = cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=fill)
    return out.astype(np.float32, copy=False), pinhole
