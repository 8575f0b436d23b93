"""Procedural solid textures.

Every texture is a function of a 3-D point in the object's own frame (a "solid" texture), never of the
pixel or the viewing direction.  That is what makes the data multi-view consistent: a surface point
has the same albedo in every view, exactly as a real Lambertian surface would, so the network has to
learn geometry to match colours across views rather than memorise images.

The noise is hashed lattice value noise (integer hash, smoothstep interpolation) so it is exactly
reproducible from a seed on any machine and needs no tables or downloads.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

PATTERNS: tuple[str, ...] = ("flat", "noise", "stripes", "checker", "gradient", "marble")


_PX, _PY, _PZ = np.uint32(73856093), np.uint32(19349663), np.uint32(83492791)


def _mix01(h: np.ndarray) -> np.ndarray:
    """murmur3 32-bit finaliser of uint32 keys -> pseudo-random values in [0, 1)."""
    h = h ^ (h >> np.uint32(16))
    h *= np.uint32(0x85EBCA6B)
    h ^= h >> np.uint32(13)
    h *= np.uint32(0xC2B2AE35)
    h ^= h >> np.uint32(16)
    return h * (1.0 / 4294967296.0)


def value_noise(p: np.ndarray, seed: int) -> np.ndarray:
    """Smooth value noise in [0, 1] at points p (N, 3), one lattice cell per unit.

    Lattice values come from an integer hash of the cell corner (uint32 arithmetic wraps
    identically everywhere), so the noise is reproducible without any tables."""
    cell = np.floor(p)
    f = p - cell
    s = f * f * (3.0 - 2.0 * f)
    i = cell.astype(np.int64).astype(np.uint32)  # two's-complement wrap of negative cells
    key = np.uint32((seed * 2654435761) & 0xFFFFFFFF)
    hx0 = i[:, 0] * _PX ^ key
    hx1 = (i[:, 0] + np.uint32(1)) * _PX ^ key
    hy0, hy1 = i[:, 1] * _PY, (i[:, 1] + np.uint32(1)) * _PY
    hz0, hz1 = i[:, 2] * _PZ, (i[:, 2] + np.uint32(1)) * _PZ
    sx, sy, sz = s[:, 0], s[:, 1], s[:, 2]

    def lerp_x(hy, hz):
        a = _mix01(hx0 ^ hy ^ hz)
        return a + (_mix01(hx1 ^ hy ^ hz) - a) * sx

    y0 = lerp_x(hy0, hz0)
    y0 += (lerp_x(hy1, hz0) - y0) * sy
    y1 = lerp_x(hy0, hz1)
    y1 += (lerp_x(hy1, hz1) - y1) * sy
    return y0 + (y1 - y0) * sz


def fbm(p: np.ndarray, seed: int, octaves: int = 4, gain: float = 0.5, contrast: float = 1.8) -> np.ndarray:
    """Fractal sum of value noise in [0, 1]; ``contrast`` re-stretches the sum, which averaging
    otherwise flattens towards 0.5."""
    total = np.zeros(len(p))
    amp, norm, freq = 1.0, 0.0, 1.0
    for k in range(octaves):
        # A fixed irrational offset per octave keeps lattice artefacts of the octaves from lining up.
        total += amp * value_noise(p * freq + 17.31 * k, seed + 1013 * k)
        norm += amp
        amp *= gain
        freq *= 2.0
    return np.clip((total / norm - 0.5) * contrast + 0.5, 0.0, 1.0)


def _soft_square(x: np.ndarray, sharpness: float) -> np.ndarray:
    """A square wave in [0, 1] with soft edges: sharp enough to look like paint, soft enough not to
    alias badly at 160x128."""
    return np.clip(0.5 + sharpness * x, 0.0, 1.0)


@dataclass(frozen=True, eq=False)
class Material:
    """Albedo pattern and reflectance of one primitive.

    ``colors`` (3, 3): a palette; patterns map a scalar field t in [0, 1] onto c0 -> c1 -> c2, or
    (binary patterns) onto c0 / c1, with c2 mixed in by noise.  ``scale`` is the pattern frequency in
    cycles per scene unit.  ``specular`` > 0 adds a small Blinn-Phong highlight, the only
    view-dependent effect in the data.  ``emissive`` surfaces (the sky) are not shaded.
    """

    pattern: str
    colors: np.ndarray
    scale: float = 1.0
    direction: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0]))
    seed: int = 0
    noise_amount: float = 0.0
    specular: float = 0.0
    shininess: float = 32.0
    emissive: bool = False


def _palette(t: np.ndarray, colors: np.ndarray) -> np.ndarray:
    t = t[:, None]
    lo = colors[0] + (colors[1] - colors[0]) * np.clip(2.0 * t, 0.0, 1.0)
    return np.where(t < 0.5, lo, colors[1] + (colors[2] - colors[1]) * np.clip(2.0 * t - 1.0, 0.0, 1.0))


def _pattern_field(m: Material, p: np.ndarray) -> tuple[np.ndarray, bool]:
    """Scalar field in [0, 1] of the pattern, and whether it is binary (two-colour)."""
    x = p @ m.direction * m.scale
    if m.pattern == "flat":
        return np.zeros(len(p)), True
    if m.pattern == "noise":
        return fbm(p * m.scale, m.seed), False
    if m.pattern == "stripes":
        return _soft_square(np.sin(2.0 * np.pi * x), 2.5), True
    if m.pattern == "checker":
        q = np.sin(np.pi * p * m.scale)
        return _soft_square(q[:, 0] * q[:, 1] * q[:, 2] * 4.0, 2.5), True
    if m.pattern == "gradient":
        return np.clip(0.5 + 0.5 * np.sin(0.5 * np.pi * x), 0.0, 1.0), False
    if m.pattern == "marble":
        return 0.5 + 0.5 * np.sin(2.0 * np.pi * x + 5.0 * fbm(p * m.scale, m.seed)), False
    raise ValueError(f"unknown pattern {m.pattern!r}")


def albedo(m: Material, p: np.ndarray) -> np.ndarray:
    """Albedo (N, 3) in [0, 1] of material ``m`` at object-frame points p (N, 3)."""
    t, binary = _pattern_field(m, p)
    if binary:
        rgb = m.colors[0] + (m.colors[1] - m.colors[0]) * t[:, None]
    else:
        rgb = _palette(t, m.colors)
    if m.noise_amount > 0.0:
        n = fbm(p * (m.scale * 3.0 + 2.0), m.seed + 7919, octaves=3)
        if binary:
            # mix the third palette colour in as grime/variation
            rgb = rgb + (m.colors[2] - rgb) * (m.noise_amount * n)[:, None]
        else:
            rgb = rgb * (1.0 + m.noise_amount * (n - 0.5))[:, None]
    return np.clip(rgb, 0.0, 1.0)


def sky_color(
    directions: np.ndarray,
    zenith: np.ndarray,
    horizon: np.ndarray,
    ground_haze: np.ndarray,
    cloud_seed: int,
    cloud_amount: float,
) -> np.ndarray:
    """Sky radiance for unit directions (N, 3) seen from the dome centre (z up): a zenith-horizon
    gradient with fbm clouds; below the horizon the haze colour, so the horizon has no seam."""
    elev = directions[:, 2]
    t = np.sqrt(np.clip(elev, 0.0, 1.0))[:, None]
    rgb = horizon + (zenith - horizon) * t
    if cloud_amount > 0.0:
        # project onto a cloud layer so clouds shrink towards the horizon, like real ones
        layer = directions[:, :2] / np.maximum(elev, 0.05)[:, None]
        pts = np.concatenate([layer * 1.5, np.zeros((len(directions), 1))], axis=1)
        c = fbm(pts, cloud_seed, octaves=5, contrast=2.2)
        c = np.clip((c - (1.0 - cloud_amount)) / max(cloud_amount, 1e-6), 0.0, 1.0) * np.clip(elev * 8.0, 0.0, 1.0)
        rgb = rgb + (np.array([0.97, 0.97, 0.98]) - rgb) * c[:, None]
    rgb = np.where(elev[:, None] < 0.0, ground_haze, rgb)
    return np.clip(rgb, 0.0, 1.0)


def random_color(
    rng: np.random.Generator,
    sat: tuple[float, float] = (0.15, 0.85),
    val: tuple[float, float] = (0.3, 0.95),
    hue: float | None = None,
) -> np.ndarray:
    """An RGB colour from HSV ranges (so saturation and brightness stay photographic)."""
    h = rng.uniform(0.0, 1.0) if hue is None else hue % 1.0
    s = rng.uniform(*sat)
    v = rng.uniform(*val)
    return _hsv_to_rgb(h, s, v)


def _hsv_to_rgb(h: float, s: float, v: float) -> np.ndarray:
    i = int(h * 6.0) % 6
    f = h * 6.0 - int(h * 6.0)
    p, q, t = v * (1 - s), v * (1 - s * f), v * (1 - s * (1 - f))
    return np.array([(v, t, p), (q, v, p), (p, v, t), (p, q, v), (t, p, v), (v, p, q)][i])


def random_material(
    rng: np.random.Generator,
    scale_range: tuple[float, float] = (1.0, 4.0),
    patterns: tuple[str, ...] = PATTERNS,
    specular_prob: float = 0.3,
    weights: tuple[float, ...] | None = None,
) -> Material:
    """A random textured material: pattern, harmonious or contrasting palette, frequency, noise."""
    pattern = str(rng.choice(patterns, p=None if weights is None else np.asarray(weights) / np.sum(weights)))
    hue = rng.uniform()
    spread = rng.choice([0.05, 0.15, 0.5])
    colors = np.stack([random_color(rng, hue=hue + k * spread * rng.uniform(0.5, 1.0)) for k in range(3)])
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    specular = float(rng.uniform(0.1, 0.35)) if rng.uniform() < specular_prob else 0.0
    return Material(
        pattern=pattern,
        colors=colors,
        scale=float(np.exp(rng.uniform(np.log(scale_range[0]), np.log(scale_range[1])))),
        direction=direction,
        seed=int(rng.integers(0, 2**31 - 1)),
        noise_amount=float(rng.choice([0.0, 0.3, 0.6])) if pattern != "noise" else 0.0,
        specular=specular,
        shininess=float(rng.uniform(16.0, 64.0)),
    )
