"""COLMAP's binary model (cameras.bin, images.bin, points3D.bin), as COLMAP writes it
(colmap/src/colmap/scene/reconstruction_io.cc): little-endian, counts as u64, ids as u32, names
NUL-terminated. The records are the ones the text model holds; :mod:`.colmap` makes cameras of
them either way."""

from __future__ import annotations

import struct
from pathlib import Path

# Binary model ids, in order, with the number of parameters (colmap/src/colmap/sensor/models.h).
MODELS = (
    ("SIMPLE_PINHOLE", 3),
    ("PINHOLE", 4),
    ("SIMPLE_RADIAL", 4),
    ("RADIAL", 5),
    ("OPENCV", 8),
    ("OPENCV_FISHEYE", 8),
    ("FULL_OPENCV", 12),
    ("FOV", 5),
    ("SIMPLE_RADIAL_FISHEYE", 4),
    ("RADIAL_FISHEYE", 5),
    ("THIN_PRISM_FISHEYE", 12),
)


class _Reader:
    def __init__(self, path: Path):
        self.path = path
        try:
            self.data = path.read_bytes()
        except FileNotFoundError:
            raise FileNotFoundError(f"COLMAP file not found: {path}") from None
        self.at = 0

    def read(self, fmt: str) -> tuple:
        size = struct.calcsize("<" + fmt)
        if self.at + size > len(self.data):
            raise ValueError(f"{self.path}: truncated binary model (wanted {size} bytes at offset {self.at})")
        values = struct.unpack_from("<" + fmt, self.data, self.at)
        self.at += size
        return values

    def count(self, record_size: int) -> int:
        """A count of records, refused when the rest of the file cannot hold that many."""
        (n,) = self.read("Q")
        if n > (len(self.data) - self.at) // record_size:
            raise ValueError(f"{self.path}: truncated binary model (record count {n} at offset {self.at - 8})")
        return n

    def name(self) -> str:
        end = self.data.find(b"\0", self.at)
        if end < 0:
            raise ValueError(f"{self.path}: truncated binary model (unterminated image name)")
        name = self.data[self.at : end].decode("utf-8", errors="replace")
        self.at = end + 1
        return name

    def skip(self, n: int, size: int) -> None:
        if self.at + n * size > len(self.data):
            raise ValueError(f"{self.path}: truncated binary model")
        self.at += n * size


def cameras(path: Path) -> list[tuple[int, str, int, int, list[float], str]]:
    """[(camera id, model, width, height, parameters, where)] of cameras.bin."""
    r = _Reader(path)
    out = []
    for k in range(r.count(24)):
        cid, model_id, width, height = r.read("IiQQ")
        if not 0 <= model_id < len(MODELS):
            raise ValueError(f"{path}: camera {cid}: unknown camera model id {model_id}")
        model, params = MODELS[model_id]
        out.append((cid, model, width, height, list(r.read(f"{params}d")), f"{path}: camera record {k}"))
    return out


def images(path: Path) -> list[tuple[int, tuple[float, ...], tuple[float, ...], int, str, str]]:
    """[(image id, qw qx qy qz, tx ty tz, camera id, name, where)] of images.bin."""
    r = _Reader(path)
    out = []
    for _ in range(r.count(73)):
        iid, *qt, cid = r.read("I7dI")
        name = r.name()
        r.skip(r.count(24), 24)  # its 2D points: x, y (f64) and point3D id (i64)
        out.append((iid, tuple(qt[:4]), tuple(qt[4:]), cid, name, f"{path}: image {name}"))
    return out


def points(path: Path) -> list[tuple[tuple[float, float, float], list[int]]]:
    """[(x y z, ids of the images that observe it)] of points3D.bin."""
    r = _Reader(path)
    out = []
    for _ in range(r.count(51)):
        _, x, y, z, *_ = r.read("Q3d3Bd")  # id, position, colour, reprojection error
        track = r.read(f"{2 * r.count(8)}I")  # (image id, 2D point index) pairs
        out.append(((x, y, z), list(track[::2])))
    return out
