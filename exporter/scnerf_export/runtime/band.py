"""The band: pixels whose surface a source does not see, coloured from the sources that do.

The model's appearance mean (F_a) divides by all V sources, a source that does not see a point
counting as zero (as it was trained). On some captures (LLFF horns, not DTU or Blender) the network
then renders a surface outside one source's image too dark: the dark band along the edges of
forward-facing views. Such a view is recognised by the ratio of the network's colours to its
sources' (each pixel's surface point, on its ray at the rendered depth, sampled bilinearly in the
sources that see it, times the pixel's opacity): lower in the band, by more than ``DARKER``, than
over the pixels every source sees. Its band's pixels then take their sources' colour, and a pixel no
source sees that of the sources' nearest pixels (their images' borders), as dark as the band in the
network's render. The server's twin is server/src/pipeline/band.rs (the band fixture
holds the two together); both compute in float64 from the float32 tensors the renderer reads.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from .. import cameras as cams
from ..cameras import Camera
from .view import Rendering

FILLS = ("sources", "network")


@dataclass
class Sources:
    """The sources as the band reads them: images (V,3,H,W) padded right and bottom, each view's own
    (width, height), K (V,3,3) and world-to-camera (V,4,4)."""

    images: np.ndarray
    sizes: list[tuple[int, int]]
    intrinsics: np.ndarray
    extrinsics: np.ndarray

    @classmethod
    def of(cls, scene: dict) -> "Sources":
        """From an encoded scene (``OnnxBundle.encode_scene``)."""
        return cls(scene["images"], scene["source_sizes"], scene["intrinsics"], scene["extrinsics"])

    @classmethod
    def of_views(cls, images: np.ndarray, cameras: list[Camera]) -> "Sources":
        """From unpadded (V,H,W,3) images and their cameras."""
        sizes = [(c.width, c.height) for c in cameras]
        return cls(images.transpose(0, 3, 1, 2), sizes, cams.stack_intrinsics(cameras), cams.stack_extrinsics(cameras))

    def project(self, v: int, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Image coordinates (N,2) of world ``points`` (N,3) in view ``v``, where they lie in front of
        it, and where inside its image as well (pixel centres at integers: [0, W-1] x [0, H-1])."""
        w2c = self.extrinsics[v].astype(np.float64)
        camera = points @ w2c[:3, :3].T + w2c[:3, 3]
        image = camera @ self.intrinsics[v].astype(np.float64).T
        with np.errstate(divide="ignore", invalid="ignore"):
            coords = image[:, :2] / image[:, 2:3]
        width, height = self.sizes[v]
        front = camera[:, 2] > 0
        inside = front & np.all(coords >= 0, axis=1) & (coords[:, 0] <= width - 1) & (coords[:, 1] <= height - 1)
        return coords, front, inside

    def sample(self, v: int, coords: np.ndarray) -> np.ndarray:
        """View ``v``'s colours (N,3) at image coordinates ``coords`` (N,2), bilinearly, clamped into the
        image."""
        width, height = self.sizes[v]
        image = self.images[v].astype(np.float64)
        col, row = np.clip(coords[:, 0], 0, width - 1), np.clip(coords[:, 1], 0, height - 1)
        x0, y0 = np.floor(col).astype(int), np.floor(row).astype(int)
        x1, y1 = np.minimum(x0 + 1, width - 1), np.minimum(y0 + 1, height - 1)
        a, b = col - x0, row - y0
        return (
            image[:, y0, x0] * (1 - a) * (1 - b)
            + image[:, y0, x1] * a * (1 - b)
            + image[:, y1, x0] * (1 - a) * b
            + image[:, y1, x1] * a * b
        ).T


# A band whose colours, against its sources', are below this fraction of the same ratio over the
# pixels every source sees is dark: between the horns views whose band is visibly dark (0.72-0.88)
# and every other validation view (0.92-1.17).
DARKER = 0.9


def surface_points(depth: np.ndarray, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Each ray's point at its z-depth (its direction has unit z in the target camera)."""
    return origins.astype(np.float64) + directions.astype(np.float64) * depth.astype(np.float64)[:, None]


def sightings(points: np.ndarray, sources: Sources) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """How many sources see each point (N,); its colour (N,3): the mean of those that see it or, where
    none does, of the nearest pixels of those it lies in front of; and where it has one (in front of
    some source)."""
    seen, border = np.zeros((len(points), 3)), np.zeros((len(points), 3))
    views, fronts = np.zeros(len(points), int), np.zeros(len(points), int)
    for v in range(len(sources.sizes)):
        coords, front, inside = sources.project(v, points)
        colour = sources.sample(v, coords[front])
        border[front] += colour
        seen[inside] += colour[inside[front]]
        views += inside
        fronts += front
    colour = np.where(views[:, None] > 0, seen / np.maximum(views, 1)[:, None], border / np.maximum(fronts, 1)[:, None])
    return views, colour, fronts > 0


def colour_ratio(rgb: np.ndarray, seen: np.ndarray, which: np.ndarray) -> float | None:
    """The sum of the network's colours over the sum of their sources' (``seen``: times opacity),
    over the pixels ``which`` selects; None where those show nothing."""
    shown = seen[which].sum()
    return float(rgb[which].astype(np.float64).sum() / shown) if shown > 0 else None


def fill_from_sources(
    rgb: np.ndarray,
    depth: np.ndarray,
    opacity: np.ndarray,
    origins: np.ndarray,
    directions: np.ndarray,
    sources: Sources,
    rule: str = "when_dark",
) -> tuple[np.ndarray, np.ndarray]:
    """The renderer's raw colours (N,3) with the band's pixels recoloured when the band is dark or the
    ``rule`` (the manifest's ``band.fill``, ``export.manifest.BAND_RULES``) is "always" (and with
    them the pixels no source sees, which keeps the band's edge at the image's edge continuous),
    and which pixels were."""
    views, colour, coloured = sightings(surface_points(depth, origins, directions), sources)
    seen = opacity[:, None].astype(np.float64) * colour
    every = len(sources.sizes)
    ratio = colour_ratio(rgb, seen, (views > 0) & (views < every))
    everywhere = colour_ratio(rgb, seen, views == every)
    dark = ratio is not None and everywhere is not None and ratio < DARKER * everywhere
    if not (dark or rule == "always"):
        return rgb, np.zeros(len(rgb), bool)
    recoloured = coloured & (views < every)
    filled = rgb.copy()
    filled[recoloured] = seen[recoloured].astype(rgb.dtype)
    return filled, recoloured


def fill_rendering(rendering: Rendering, target: Camera, scene: dict, background, rule: str = "when_dark") -> Rendering:
    """A composited view with its band recoloured from the encoded ``scene``'s sources by ``rule``, as
    the server does between its renderer and the composite."""
    bg = np.asarray(background, np.float32)
    opacity = rendering.opacity.reshape(-1)
    transparency = (1.0 - opacity)[:, None] * bg
    raw = rendering.rgb.reshape(-1, 3) - transparency
    origins, directions = cams.target_rays(target)
    depth = rendering.depth.reshape(-1)
    filled, band = fill_from_sources(raw, depth, opacity, origins, directions, Sources.of(scene), rule)
    rgb = np.where(band[:, None], filled + transparency, rendering.rgb.reshape(-1, 3))
    return replace(rendering, rgb=rgb.reshape(rendering.rgb.shape).astype(rendering.rgb.dtype))
