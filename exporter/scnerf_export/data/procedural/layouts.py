"""Scene layouts: what is in the scene, where the cameras are, and the scene's [near, far].

World frame: z up, metres-ish units.  Each layout mimics one family of real data the paper cares
about:

* ``object``  (DTU-like): a few objects on a round table, cameras on a sphere cap around them looking
  at the centre from a distance of 3.1-3.5; [near, far] is the z-range of a ball of radius 1.2 around
  the look-at point in every view, which gives DTU's ~2.1 / ~4.5 (MVSNeRF's 1/200-scaled DTU uses
  2.125 / 4.525).  Empty space is black with alpha 0.
* ``forward`` (LLFF-like): cameras on a small jittered grid facing +y (slightly converging), layered
  objects from ~2 units to a back wall at 8-12, a floor; everything is opaque.  near 1.2-2.7,
  far 10-14 (far/near 5-10), from a depth probe with margins (near = 0.8 min, far = 1.15 max).
* ``outdoor`` (Spaces-like): a ground plane, buildings, trees, poles and rocks from 3 to 100 units,
  an emissive sky dome of radius 150-300 as the far background, world-space haze, cameras at eye
  height spread over 2-6 units with yaw/pitch jitter.  near 1.3-2.6, far 157-306 (far/near 75-240;
  near = 0.75 min probe depth, far = 1.03 max: the dome sits just inside the far plane).

Geometry is drawn from one generator and camera poses from another (both children of the scene's
seed), so the scene itself does not change with ``n_views``, and neither does anything (including
near/far, measured on a fixed-size depth probe) with the output resolution at a given aspect ratio.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .core import ALL_LAYOUTS, Camera, intrinsics, look_at, yaw_pitch_w2c
from .geometry import Box, Cylinder, Plane, Primitive, SkyDome, Sphere, rotation_from_euler
from .raytrace import Haze, Light, World, trace_depth
from .textures import Material, random_color, random_material

OBJECT_BALL_RADIUS = 1.2
OBJECT_TARGET = np.array([0.0, 0.0, 0.3])
PROBE_WIDTH = 96


# ----------------------------------------------------------------------------------------------
# shared helpers


def _sun(
    rng: np.random.Generator,
    elevation_deg: tuple[float, float],
    ambient: tuple[float, float],
    toward_deg: float,
    spread_deg: float,
) -> Light:
    """A directional light whose azimuth is within ``spread_deg`` of ``toward_deg`` (the side the
    cameras are on), so most visible faces are lit, as in most photographs."""
    az = np.radians(toward_deg + rng.uniform(-spread_deg, spread_deg))
    el = np.radians(rng.uniform(*elevation_deg))
    direction = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    warmth = rng.uniform(-0.08, 0.08)
    color = np.array([1.0 + warmth, 1.0, 1.0 - warmth])
    return Light(
        direction=direction, color=color, ambient=float(rng.uniform(*ambient)), diffuse=float(rng.uniform(0.6, 0.8))
    )


def _random_shape(
    rng: np.random.Generator, size: float, base: np.ndarray, material: Material, upright: bool
) -> tuple[Primitive, float]:
    """A box, sphere or cylinder of roughly ``size`` resting on z = base[2] (if ``upright``) or
    freely rotated around ``base``; returns the primitive and its bounding radius."""
    kind = rng.choice(["box", "sphere", "cylinder"], p=[0.4, 0.3, 0.3])
    if kind == "sphere":
        r = size * rng.uniform(0.7, 1.0)
        center = base + np.array([0.0, 0.0, r if upright else 0.0])
        return Sphere(center=center, material=material, radius=r), r
    if upright:
        rot = rotation_from_euler(rng.uniform(0, 2 * np.pi))
    else:
        rot = rotation_from_euler(*rng.uniform(0, 2 * np.pi, size=3))
    if kind == "box":
        half = size * rng.uniform(0.4, 1.0, size=3)
        center = base + np.array([0.0, 0.0, half[2] if upright else 0.0])
        return Box(center=center, material=material, rotation=rot, half=half), float(np.linalg.norm(half))
    r = size * rng.uniform(0.35, 0.8)
    hh = size * rng.uniform(0.4, 1.1)
    center = base + np.array([0.0, 0.0, hh if upright else 0.0])
    return Cylinder(center=center, material=material, rotation=rot, radius=r, half_height=hh), float(np.hypot(r, hh))


def _grid(rng: np.random.Generator, n: int, aspect: float, jitter: float) -> np.ndarray:
    """n points in [0, 1]^2 on a jittered grid with about ``aspect`` columns per row."""
    rows = max(1, int(round(np.sqrt(n / aspect))))
    cols = int(np.ceil(n / rows))
    pts = []
    for r in range(rows):
        for c in range(cols):
            pts.append(
                ((c + 0.5 + rng.uniform(-jitter, jitter)) / cols, (r + 0.5 + rng.uniform(-jitter, jitter)) / rows)
            )
    pts = np.array(pts[:n])
    return np.clip(pts, 0.0, 1.0)


def _probe_range(world: World, cameras: list[Camera]) -> tuple[float, float]:
    """Min and max finite z-depth over all views on a fixed-size probe grid."""
    lo, hi = np.inf, 0.0
    for cam in cameras:
        d = trace_depth(world, cam, width=PROBE_WIDTH)
        d = d[np.isfinite(d)]
        if d.size:
            lo, hi = min(lo, float(d.min())), max(hi, float(d.max()))
    return lo, hi


# ----------------------------------------------------------------------------------------------
# object (DTU-like)


def _object_world(rng: np.random.Generator, cam_azimuth: float) -> World:
    table_mat = random_material(
        rng, scale_range=(2.0, 6.0), specular_prob=0.1, patterns=("noise", "checker", "stripes", "marble", "flat")
    )
    table_r = rng.uniform(0.9, 1.05)
    prims: list[Primitive] = [
        Cylinder(center=np.array([0.0, 0.0, -0.05]), material=table_mat, radius=table_r, half_height=0.05)
    ]
    n_obj = int(rng.integers(3, 8))
    tries = 0
    while len(prims) < n_obj + 1 and tries < 100:
        tries += 1
        rad = 0.65 * np.sqrt(rng.uniform())
        ang = rng.uniform(0, 2 * np.pi)
        base = np.array([rad * np.cos(ang), rad * np.sin(ang), 0.0])
        if rng.uniform() < 0.2:  # a few floating objects, like things on stands
            base[2] = rng.uniform(0.2, 0.5)
        mat = random_material(rng, scale_range=(3.0, 12.0))
        prim, bound = _random_shape(rng, rng.uniform(0.12, 0.35), base, mat, upright=True)
        if np.linalg.norm(prim.center - OBJECT_TARGET) + bound <= OBJECT_BALL_RADIUS:
            prims.append(prim)
    return World(primitives=prims, light=_sun(rng, (30.0, 75.0), (0.35, 0.5), np.degrees(cam_azimuth), 100.0))


@dataclasses.dataclass(frozen=True)
class Arc:
    """Where a layout's cameras stand: rows on an arc around ``target``, facing it, as DTU's robot
    arm and object captures place them. Each scene draws its distance, azimuth span and elevations
    (degrees) from these ranges; each camera jitters its distance and the point it aims at."""

    target: np.ndarray
    distance: tuple[float, float]
    azimuth_span: tuple[float, float]
    elevation_low: tuple[float, float]
    elevation_high: tuple[float, float]
    aspect: float
    grid_jitter: float
    distance_jitter: float
    aim_jitter: float


def _arc_cameras(
    rng: np.random.Generator, arc: Arc, n: int, width: int, height: int, hfov: float, az0: float
) -> list[Camera]:
    # The draws keep one order (distance, span, elevations, grid, then per camera), so a seed
    # gives the same scene whatever the layout's ranges.
    dist = rng.uniform(*arc.distance)
    az_span = np.radians(rng.uniform(*arc.azimuth_span))
    el_lo, el_hi = np.radians(rng.uniform(*arc.elevation_low)), np.radians(rng.uniform(*arc.elevation_high))
    K = intrinsics(width, height, hfov)
    cams = []
    for gx, gy in _grid(rng, n, aspect=arc.aspect, jitter=arc.grid_jitter):
        az = az0 + (gx - 0.5) * az_span
        el = el_lo + gy * (el_hi - el_lo)
        r = dist + rng.uniform(-arc.distance_jitter, arc.distance_jitter)
        eye = arc.target + r * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        aim = arc.target + rng.normal(0.0, arc.aim_jitter, size=3)
        cams.append(Camera(K=K.copy(), w2c=look_at(eye, aim), width=width, height=height))
    return cams


OBJECT_ARC = Arc(OBJECT_TARGET, (3.1, 3.5), (80.0, 140.0), (15.0, 25.0), (45.0, 60.0), 2.5, 0.3, 0.1, 0.04)


def _object_near_far(cameras: list[Camera]) -> tuple[float, float]:
    zc = [float(cam.w2c[2, :3] @ OBJECT_TARGET + cam.w2c[2, 3]) for cam in cameras]
    return min(zc) - OBJECT_BALL_RADIUS, max(zc) + OBJECT_BALL_RADIUS


# ----------------------------------------------------------------------------------------------
# tabletop (photo-like, DTU's framing)

TABLETOP_TARGET = np.array([0.0, 0.0, 0.2])
TABLETOP_HFOV = (26.0, 32.0)  # DTU's 640x512 crops see ~25 degrees: objects fill the frame


def _tabletop_world(rng: np.random.Generator, cam_azimuth: float) -> World:
    """A square table with a wood, stone or cloth texture, four to eight textured objects on it, a
    sun from the cameras' side with cast shadows; beyond the table the void is black, like DTU's."""
    table_mat = random_material(
        rng,
        scale_range=(1.5, 5.0),
        specular_prob=0.15,
        patterns=("noise", "marble", "stripes", "checker"),
        weights=(3, 3, 2, 1),
    )
    table_mat = dataclasses.replace(
        table_mat, colors=np.stack([random_color(rng, sat=(0.1, 0.45), val=(0.35, 0.85)) for _ in range(3)])
    )
    half = rng.uniform(1.4, 1.8)
    prims: list[Primitive] = [
        Box(
            center=np.array([0.0, 0.0, -0.05]),
            material=table_mat,
            rotation=rotation_from_euler(rng.uniform(0, 2 * np.pi)),
            half=np.array([half, half, 0.05]),
        )
    ]
    n_obj = int(rng.integers(4, 9))
    tries = 0
    while len(prims) < n_obj + 1 and tries < 200:
        tries += 1
        rad = 0.7 * np.sqrt(rng.uniform())
        ang = rng.uniform(0, 2 * np.pi)
        base = np.array([rad * np.cos(ang), rad * np.sin(ang), 0.0])
        mat = random_material(rng, scale_range=(4.0, 16.0), specular_prob=0.35)
        prim, bound = _random_shape(rng, rng.uniform(0.15, 0.4), base, mat, upright=True)
        if all(np.linalg.norm(prim.center[:2] - q.center[:2]) > 0.6 * (bound + q.bound) for q in prims[1:]):
            prims.append(prim)
    light = _sun(rng, (35.0, 70.0), (0.25, 0.4), np.degrees(cam_azimuth), 70.0)
    return World(primitives=prims, light=light, shadows=True)


TABLETOP_ARC = Arc(TABLETOP_TARGET, (3.0, 3.4), (90.0, 120.0), (18.0, 25.0), (40.0, 50.0), 3.0, 0.2, 0.05, 0.03)


# ----------------------------------------------------------------------------------------------
# forward (LLFF-like)


def _wall(y: float, material: Material) -> Plane:
    # local x = world x, local y = world z, local z (normal) = world -y
    rot = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    return Plane(center=np.array([0.0, y, 0.0]), material=material, rotation=rot)


def _forward_world(rng: np.random.Generator, hfov: float, cam_height: float) -> World:
    back = rng.uniform(8.0, 12.0)
    wall_mat = random_material(
        rng, scale_range=(0.3, 1.5), specular_prob=0.0, patterns=("noise", "stripes", "checker", "marble", "gradient")
    )
    floor_mat = random_material(
        rng, scale_range=(0.5, 3.0), specular_prob=0.1, patterns=("noise", "checker", "stripes", "marble")
    )
    prims: list[Primitive] = [_wall(back, wall_mat), Plane(center=np.zeros(3), material=floor_mat)]
    tan_h = np.tan(np.radians(hfov) / 2.0)
    tan_v = tan_h * 0.8  # placement assumes 5:4 frames so the scene does not depend on the output size
    n_obj = int(rng.integers(7, 13))
    depths = np.sort(rng.uniform(2.2, back - 1.0, size=n_obj))
    for y in depths:
        size = y * rng.uniform(0.07, 0.14)
        x = rng.uniform(-0.8, 0.8) * y * tan_h
        if rng.uniform() < 0.3:
            base, upright = np.array([x, y, 0.0]), True
        else:  # most objects float around eye level, where LLFF-style captures point
            z = cam_height + rng.uniform(-0.6, 0.5) * y * tan_v
            base, upright = np.array([x, y, max(z, 1.2 * size)]), False
        mat = random_material(rng, scale_range=(1.0 / size * 0.3, 1.0 / size * 1.5))
        prims.append(_random_shape(rng, size, base, mat, upright=upright)[0])
    return World(primitives=prims, light=_sun(rng, (30.0, 75.0), (0.35, 0.5), -90.0, 100.0))


def _forward_cameras(
    rng: np.random.Generator, n: int, width: int, height: int, hfov: float, cam_height: float
) -> list[Camera]:
    bw = rng.uniform(0.5, 1.0)
    bh = bw * rng.uniform(0.5, 0.8)
    focus = np.array([0.0, rng.uniform(6.0, 15.0), cam_height])
    K = intrinsics(width, height, hfov)
    cams = []
    for gx, gy in _grid(rng, n, aspect=1.3, jitter=0.25):
        eye = np.array([(gx - 0.5) * bw, rng.uniform(-0.05, 0.05), cam_height + (0.5 - gy) * bh])
        target = focus + rng.normal(0.0, 0.15, size=3)
        cams.append(Camera(K=K.copy(), w2c=look_at(eye, target), width=width, height=height))
    return cams


# ----------------------------------------------------------------------------------------------
# outdoor (Spaces-like)


def _earthy_material(rng: np.random.Generator, scale_range: tuple[float, float]) -> Material:
    hue = rng.choice([0.08, 0.1, 0.22, 0.28, 0.3, 0.12]) + rng.uniform(-0.03, 0.03)
    colors = np.stack(
        [random_color(rng, sat=(0.2, 0.6), val=(0.25, 0.6), hue=hue + rng.uniform(-0.05, 0.05)) for _ in range(3)]
    )
    return Material(
        pattern="noise",
        colors=colors,
        scale=float(np.exp(rng.uniform(np.log(scale_range[0]), np.log(scale_range[1])))),
        seed=int(rng.integers(0, 2**31 - 1)),
    )


def _foliage_material(rng: np.random.Generator) -> Material:
    colors = np.stack(
        [random_color(rng, sat=(0.35, 0.8), val=(0.15, 0.55), hue=rng.uniform(0.18, 0.38)) for _ in range(3)]
    )
    return Material(
        pattern="noise", colors=colors, scale=float(rng.uniform(1.5, 4.0)), seed=int(rng.integers(0, 2**31 - 1))
    )


def _building_material(rng: np.random.Generator) -> Material:
    m = random_material(
        rng,
        scale_range=(0.25, 1.0),
        specular_prob=0.2,
        patterns=("stripes", "checker", "noise", "flat", "marble"),
        weights=(3, 3, 2, 1, 1),
    )
    # facades: mostly unsaturated, with real grime
    colors = 0.5 * m.colors + 0.5 * m.colors.mean(axis=1, keepdims=True)
    axis = np.array([0.0, 0.0, 1.0]) if rng.uniform() < 0.5 else np.array([1.0, 0.0, 0.0])
    return Material(
        pattern=m.pattern,
        colors=colors,
        scale=m.scale,
        direction=axis,
        seed=m.seed,
        noise_amount=max(m.noise_amount, 0.3),
        specular=m.specular,
        shininess=m.shininess,
    )


def _outdoor_world(rng: np.random.Generator, hfov: float) -> World:
    tan_h = np.tan(np.radians(hfov) / 2.0)
    prims: list[Primitive] = [Plane(center=np.zeros(3), material=_earthy_material(rng, (0.3, 1.5)))]
    if rng.uniform() < 0.5:  # a road running away from the cameras
        road = random_material(rng, scale_range=(0.2, 0.6), patterns=("stripes", "noise"), specular_prob=0.0)
        grey = road.colors.mean(axis=1, keepdims=True) * np.array([[0.6], [0.6], [1.2]])
        road = Material(
            pattern=road.pattern,
            colors=np.clip(0.7 * grey + 0.3 * road.colors, 0, 1),
            scale=road.scale,
            direction=np.array([1.0, 0.0, 0.0]),
            seed=road.seed,
            noise_amount=0.6,
        )
        prims.append(
            Plane(
                center=np.array([rng.uniform(-4.0, 4.0), 0.0, 0.01]),
                material=road,
                half=(float(rng.uniform(1.5, 4.0)), np.inf),
            )
        )

    def spot(y_lo: float, y_hi: float, spread: float = 1.1) -> tuple[float, float]:
        y = float(np.exp(rng.uniform(np.log(y_lo), np.log(y_hi))))
        return float(rng.uniform(-spread, spread) * y * tan_h), y

    for _ in range(int(rng.integers(3, 9))):  # buildings
        x, y = spot(18.0, 90.0)
        half = np.array([rng.uniform(2.0, 8.0), rng.uniform(2.0, 8.0), rng.uniform(2.0, 12.0)])
        prims.append(
            Box(
                center=np.array([x, y + half[1], half[2]]),
                material=_building_material(rng),
                rotation=rotation_from_euler(rng.uniform(-0.35, 0.35)),
                half=half,
            )
        )
    for _ in range(int(rng.integers(3, 11))):  # trees
        x, y = spot(6.0, 50.0)
        trunk_h = rng.uniform(1.0, 2.0)
        trunk_mat = _earthy_material(rng, (3.0, 8.0))
        prims.append(
            Cylinder(
                center=np.array([x, y, trunk_h]),
                material=trunk_mat,
                radius=float(rng.uniform(0.15, 0.35)),
                half_height=trunk_h,
            )
        )
        crown = rng.uniform(1.0, 2.8)
        prims.append(
            Sphere(center=np.array([x, y, 2 * trunk_h + 0.7 * crown]), material=_foliage_material(rng), radius=crown)
        )
    for _ in range(int(rng.integers(1, 5))):  # poles
        x, y = spot(5.0, 30.0)
        hh = rng.uniform(1.5, 4.0)
        prims.append(
            Cylinder(
                center=np.array([x, y, hh]),
                material=random_material(rng, (1.0, 4.0)),
                radius=float(rng.uniform(0.06, 0.18)),
                half_height=hh,
            )
        )
    for _ in range(int(rng.integers(2, 7))):  # rocks, crates and other near props
        x, y = spot(3.5, 15.0, spread=0.9)
        size = rng.uniform(0.25, 0.9)
        if rng.uniform() < 0.5:
            prims.append(
                Sphere(
                    center=np.array([x, y, size * rng.uniform(-0.3, 0.4)]),
                    material=_earthy_material(rng, (1.0, 4.0)),
                    radius=size,
                )
            )
        else:
            prims.append(
                _random_shape(rng, size, np.array([x, y, 0.0]), random_material(rng, (1.0, 5.0)), upright=True)[0]
            )

    overcast = rng.uniform() < 0.25
    if overcast:
        g = rng.uniform(0.6, 0.85)
        zenith, horizon = np.array([g, g, g + 0.03]), np.array([g + 0.08, g + 0.08, g + 0.1])
    else:
        zenith = np.array([rng.uniform(0.15, 0.4), rng.uniform(0.35, 0.6), rng.uniform(0.75, 0.95)])
        horizon = np.array([rng.uniform(0.7, 0.85), rng.uniform(0.78, 0.9), rng.uniform(0.85, 0.97)])
    horizon = np.clip(horizon, 0.0, 1.0)
    dome_r = float(rng.uniform(150.0, 300.0))
    sky_mat = Material(pattern="flat", colors=np.stack([horizon] * 3), emissive=True)
    prims.append(
        SkyDome(
            center=np.zeros(3),
            material=sky_mat,
            radius=dome_r,
            zenith=zenith,
            horizon=horizon,
            cloud_seed=int(rng.integers(0, 2**31 - 1)),
            cloud_amount=float(rng.uniform(0.0, 0.6)) if not overcast else 0.0,
        )
    )
    haze = Haze(color=horizon * 0.95, center=np.array([0.0, 0.0, 0.0]), distance=float(rng.uniform(80.0, 220.0)))
    return World(primitives=prims, light=_sun(rng, (20.0, 70.0), (0.4, 0.55), -90.0, 130.0), haze=haze)


def _outdoor_cameras(rng: np.random.Generator, n: int, width: int, height: int, hfov: float) -> list[Camera]:
    span = rng.uniform(2.0, 6.0)
    depth_span = span * rng.uniform(0.2, 0.5)
    height0 = rng.uniform(1.4, 2.0)
    pitch0 = np.radians(rng.uniform(-6.0, 3.0))
    K = intrinsics(width, height, hfov)
    cams = []
    for gx, gy in _grid(rng, n, aspect=3.0, jitter=0.3):
        eye = np.array([(gx - 0.5) * span, (gy - 0.5) * depth_span, height0 + rng.uniform(-0.3, 0.3)])
        yaw = np.radians(rng.normal(0.0, 5.0)) - 0.02 * eye[0]  # slight toe-in, like a rig
        pitch = pitch0 + np.radians(rng.normal(0.0, 1.5))
        cams.append(Camera(K=K.copy(), w2c=yaw_pitch_w2c(eye, yaw, pitch), width=width, height=height))
    return cams


# ----------------------------------------------------------------------------------------------


def build_layout(
    seed: int, layout: str, n_views: int, width: int, height: int
) -> tuple[World, list[Camera], float, float]:
    """World, cameras and [near, far] of scene ``seed`` in ``layout`` (nothing rendered yet)."""
    if layout not in ALL_LAYOUTS:
        raise ValueError(f"layout must be one of {ALL_LAYOUTS}, got {layout!r}")
    world_seq, cam_seq = np.random.SeedSequence([int(seed), ALL_LAYOUTS.index(layout)]).spawn(2)
    wrng, crng = np.random.default_rng(world_seq), np.random.default_rng(cam_seq)
    if layout == "object":
        hfov = float(wrng.uniform(40.0, 46.0))
        az0 = float(wrng.uniform(0.0, 2.0 * np.pi))  # where the cameras stand (the light follows)
        world = _object_world(wrng, az0)
        cams = _arc_cameras(crng, OBJECT_ARC, n_views, width, height, hfov, az0)
        near, far = _object_near_far(cams)
    elif layout == "tabletop":
        hfov = float(wrng.uniform(*TABLETOP_HFOV))
        az0 = float(wrng.uniform(0.0, 2.0 * np.pi))
        world = _tabletop_world(wrng, az0)
        cams = _arc_cameras(crng, TABLETOP_ARC, n_views, width, height, hfov, az0)
        lo, hi = _probe_range(world, cams)
        near, far = 0.9 * lo, 1.05 * hi
    elif layout == "forward":
        hfov = float(wrng.uniform(50.0, 65.0))
        cam_height = float(wrng.uniform(0.8, 1.6))
        world = _forward_world(wrng, hfov, cam_height)
        cams = _forward_cameras(crng, n_views, width, height, hfov, cam_height)
        lo, hi = _probe_range(world, cams)
        near, far = 0.8 * lo, 1.15 * hi
    else:
        hfov = float(wrng.uniform(55.0, 75.0))
        world = _outdoor_world(wrng, hfov)
        cams = _outdoor_cameras(crng, n_views, width, height, hfov)
        lo, hi = _probe_range(world, cams)
        near, far = 0.75 * lo, 1.03 * hi
    return world, cams, float(near), float(far)
