"""Ray banks for `scnerf-export refine`: what the trunk (M1) and the heads read for rays of a
capture's views, computed once per view with the encoder and volume frozen.

The finetune command banks F_r, the trunk's output (``finetune.RayBank``); refine banks the
trunk's inputs instead, so that M1 can train as well: per sample the reference-frustum
coordinates x (M1 reads E(x)), the point features f (M1's gate and the geometry rectifier's
keys) and the appearance features (the appearance rectifier's keys), per ray its direction in
the reference frame. A step then runs M1 and the heads on banked rays, never G1 or G2.

Each view is encoded as the server encodes it: its 3 sources through the bundle's own encoder and
volume graphs in ONNX Runtime (``OnnxBundle.encode_scene``: padding, the plane sweep by
``sweep_in_torch``), the S uniform samples of [near, far] on rays through pixel centres,
``depth_range = [near, far]``. Validation and held-out views are scored as the server renders
them, the band stage included (``score``: by each of its rules).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from .. import cameras as cams
from ..data.scene import View
from ..export.manifest import BAND_RULES
from ..model.cost_volume import build_cost_volume
from ..model.layers import frequency_encoding
from ..model.points import reference_frustum_coordinates, sample_views, sample_volume
from ..model.renderer import RadiancePoints, RayRenderer, uniform_depths
from ..runtime.band import Sources, fill_from_sources
from .from_scratch import psnr_from_mse


@torch.no_grad()
def sweep_in_torch(
    features: np.ndarray,
    images: np.ndarray,
    projections: np.ndarray,
    depth_planes: np.ndarray,
    plane_inside: np.ndarray,
    pad: int,
) -> np.ndarray:
    """The plane sweep by the cost volume's definition (``build_cost_volume``), zero on the halo
    planes outside the volume: within float rounding of the server's arithmetic (runtime/plane_sweep.py),
    and about 4x faster than it on 2 cores (grid_sample is threaded), which is what banking needs."""
    tensors = (torch.from_numpy(np.ascontiguousarray(x)) for x in (features, images, projections, depth_planes))
    cost = build_cost_volume(*tensors, pad).numpy()
    cost[:, :, np.asarray(plane_inside) == 0] = 0.0
    return cost


@dataclass
class PointBank:
    """Banked rays (of one view or many) and the truth they are compared with."""

    frustum: torch.Tensor  # x in the reference frustum (N,S,3) float32
    point_features: torch.Tensor  # f (N,F,S) float16
    appearance: torch.Tensor  # mean [F_i, I_i] over the sources (N,A,S) float16; (N,0,S) without it
    ref_dir: torch.Tensor  # (N,3)
    origins: torch.Tensor  # (N,3) the rays in the world, as cameras.target_rays gives them (the band reads them)
    directions: torch.Tensor  # (N,3)
    truth: torch.Tensor  # (N,3) the view's colours
    mask: torch.Tensor  # (N) bool: object pixel (DTU's masks), True where the view has none
    view: torch.Tensor  # (N) index of the view each ray belongs to
    z: torch.Tensor  # (S) sample depths, shared by every ray of a capture
    depth_range: torch.Tensor  # (2) the rectifiers' depth range, [near, far]
    background: torch.Tensor  # (3)

    FORMAT = 2  # in a bank file's name: a bank of other fields is banked again, not read
    PER_RAY = ("frustum", "point_features", "appearance", "ref_dir", "origins", "directions", "truth", "mask", "view")

    def __len__(self) -> int:
        return self.truth.shape[0]

    def rays(self, keep: torch.Tensor) -> PointBank:
        """The bank's rays ``keep`` (indices or a mask)."""
        shared = {k: v for k, v in self.__dict__.items() if k not in self.PER_RAY}
        return PointBank(**{k: getattr(self, k)[keep] for k in self.PER_RAY}, **shared)

    def storable(self) -> PointBank:
        """Without rays whose features overflow float16 (they would make every step that draws them NaN)."""
        finite = torch.isfinite(self.point_features).flatten(1).all(dim=1)
        return self.rays(finite & torch.isfinite(self.appearance).flatten(1).all(dim=1))

    @staticmethod
    def concat(banks: list[PointBank]) -> PointBank:
        """One bank of every ray of ``banks``, their ``view`` indices kept (each bank names its own)."""
        fields = {k: torch.cat([getattr(b, k) for b in banks]) for k in PointBank.PER_RAY}
        shared = {k: getattr(banks[0], k) for k in ("z", "depth_range", "background")}
        return PointBank(**fields, **shared)


@dataclass(frozen=True)
class Encoded:
    """A source triple through G1 and G2 (numpy, as ``OnnxBundle.encode_scene`` returns it)."""

    images: torch.Tensor
    features: torch.Tensor
    volume: torch.Tensor
    intrinsics: torch.Tensor
    extrinsics: torch.Tensor

    @staticmethod
    def of(scene: dict[str, np.ndarray]) -> Encoded:
        return Encoded(**{k: torch.from_numpy(np.ascontiguousarray(scene[k])) for k in Encoded.__dataclass_fields__})


def trunk_inputs(
    renderer: RayRenderer, encoded: Encoded, origins: torch.Tensor, directions: torch.Tensor, near_far: torch.Tensor
) -> tuple[torch.Tensor, ...]:
    """What ``RayRenderer.radiance_points`` computes before M1, for rays at the S uniform depths:
    frustum coordinates (R,S,3), f (R,F,S), appearance features (R,A,S) and the ray directions in
    the reference frame (R,3)."""
    cfg = renderer.cfg
    rays, samples = origins.shape[0], cfg.samples
    z = uniform_depths(near_far, samples)
    points = (origins[:, None, :] + directions[:, None, :] * z[None, :, None]).reshape(-1, 3)
    _, _, height, width = encoded.images.shape
    intrinsics, extrinsics = encoded.intrinsics, encoded.extrinsics
    frustum = reference_frustum_coordinates(points, intrinsics[0], extrinsics[0], near_far, height, width, cfg.pad)
    s = sample_volume(encoded.volume, frustum)
    features = encoded.features if renderer.appearance is not None else None
    colours, appearance = sample_views(points, encoded.images, features, intrinsics, extrinsics)
    if appearance is None:
        appearance = torch.zeros((0, rays * samples))
    unit = directions / torch.linalg.vector_norm(directions, dim=-1, keepdim=True)

    def per_ray(x: torch.Tensor) -> torch.Tensor:  # (K, R*S) -> (R,K,S)
        return x.view(x.shape[0], rays, samples).transpose(0, 1)

    return (
        frustum.view(rays, samples, 3),
        per_ray(torch.cat([s, colours])),
        per_ray(appearance),
        unit @ extrinsics[0, :3, :3].transpose(0, 1),
    )


@torch.no_grad()
def bank_view(
    renderer: RayRenderer,
    encoded: Encoded,
    view: View,
    pick: np.ndarray,
    near: float,
    far: float,
    background,
    index: int,
    chunk: int = 1024,
) -> PointBank:
    """The banked rays of the pixels ``pick`` (flat indices) of ``view``, seen from ``encoded``."""
    origins, directions = cams.target_rays(view.camera)
    near_far = torch.tensor([near, far], dtype=torch.float32)
    parts = []
    for start in range(0, len(pick), chunk):
        rows = pick[start : start + chunk]
        o, d = torch.from_numpy(origins[rows]), torch.from_numpy(directions[rows])
        frustum, f, appearance, ref_dir = trunk_inputs(renderer, encoded, o, d, near_far)
        parts.append((frustum, f.half(), appearance.half(), ref_dir))
    n = len(pick)
    mask = np.ones(n, dtype=bool) if view.mask is None else view.mask.reshape(-1)[pick]
    return PointBank(
        frustum=torch.cat([p[0] for p in parts]),
        point_features=torch.cat([p[1] for p in parts]),
        appearance=torch.cat([p[2] for p in parts]),
        ref_dir=torch.cat([p[3] for p in parts]),
        origins=torch.from_numpy(origins[pick]),
        directions=torch.from_numpy(directions[pick]),
        truth=torch.from_numpy(view.image.reshape(-1, 3)[pick].astype(np.float32)),
        mask=torch.from_numpy(mask),
        view=torch.full((n,), index, dtype=torch.long),
        z=uniform_depths(near_far, renderer.cfg.samples),
        depth_range=near_far,
        background=torch.tensor(background, dtype=torch.float32),
    ).storable()


def device_of(renderer: RayRenderer) -> torch.device:
    return next(renderer.parameters()).device


def radiance_points(renderer: RayRenderer, bank: PointBank, idx: torch.Tensor) -> RadiancePoints:
    """The rays ``idx`` through M1 (with gradients when enabled): what the heads read. The bank
    stays where it is (host memory); the rays drawn go to the renderer's device."""
    rays, device = idx.shape[0], device_of(renderer)

    def drawn(x: torch.Tensor) -> torch.Tensor:
        return x[idx].to(device, non_blocking=True)

    def channels_first(x: torch.Tensor) -> torch.Tensor:  # (R,K,S) -> (K, R*S)
        return drawn(x).float().transpose(0, 1).reshape(x.shape[1], -1)

    f = channels_first(bank.point_features)
    encoding = frequency_encoding(drawn(bank.frustum).reshape(-1, 3), renderer.cfg.position_freqs)
    appearance = channels_first(bank.appearance) if renderer.appearance is not None else None
    radiance = renderer.m1(encoding, f.transpose(0, 1))
    z = bank.z.to(device)
    return RadiancePoints(z, radiance.view(rays * z.shape[0], -1), f, appearance, drawn(bank.ref_dir))


def shade(renderer: RayRenderer, bank: PointBank, idx: torch.Tensor) -> torch.Tensor:
    """Composited colour of the rays ``idx``, as the server composites it on the background (on
    the renderer's device)."""
    device = device_of(renderer)
    rgb, _, opacity = renderer.shade(radiance_points(renderer, bank, idx), bank.depth_range.to(device))
    return rgb + (1.0 - opacity[:, None]) * bank.background.to(device)


@torch.no_grad()
def render_raw(renderer: RayRenderer, bank: PointBank, chunk: int = 1024) -> tuple[np.ndarray, ...]:
    """Every ray of the bank before the composite, as the band stage reads them: colours (N,3),
    depth D and opacity (N), float64."""
    parts = []
    for start in range(0, len(bank), chunk):
        rgb, depth, opacity = renderer.shade(
            radiance_points(renderer, bank, torch.arange(start, min(start + chunk, len(bank)))),
            bank.depth_range.to(device_of(renderer)),
        )
        parts.append((rgb.cpu(), depth.cpu(), opacity.cpu()))
    return tuple(torch.cat([p[k] for p in parts]).double().numpy() for k in range(3))


def composite(bank: PointBank, rgb: np.ndarray, opacity: np.ndarray) -> np.ndarray:
    """Colours on the background, clamped to [0,1] as the server's 8-bit output is."""
    return np.clip(rgb + (1.0 - opacity[:, None]) * bank.background.double().numpy(), 0.0, 1.0)


def band_filled(bank: PointBank, raw: tuple[np.ndarray, ...], sources: list[Sources], rule: str) -> np.ndarray:
    """The raw colours with each view's band recoloured from its sources (``sources[i]`` for view
    i) by ``rule``, as the server's band stage does (judged on the bank's pixels of the view)."""
    rgb, depth, opacity = raw
    filled = rgb.copy()
    for i, view_sources in enumerate(sources):
        rows = (bank.view == i).numpy()
        o, d = bank.origins[rows].numpy(), bank.directions[rows].numpy()
        filled[rows] = fill_from_sources(rgb[rows], depth[rows], opacity[rows], o, d, view_sources, rule)[0]
    return filled


def score_colours(bank: PointBank, colours: np.ndarray, names: list[str]) -> dict:
    """PSNR of each view's banked pixels (``names[i]`` for view i), their mean, and the same on the
    object pixels of views with masks (DTU's protocol)."""
    error = ((colours - bank.truth.double().numpy()) ** 2).mean(axis=1)
    view, mask = bank.view.numpy(), bank.mask.numpy()
    views, masked = {}, {}
    for i, name in enumerate(names):
        rows = view == i
        views[name] = psnr_from_mse(float(error[rows].mean()))
        if not mask[rows].all():
            masked[name] = psnr_from_mse(float(error[rows & mask].mean()))
    out = {"psnr": float(np.mean(list(views.values()))), "views": views}
    if masked:
        out["psnr_masked"] = float(np.mean(list(masked.values())))
        out["views_masked"] = masked
    return out


def score(
    renderer: RayRenderer,
    bank: PointBank,
    names: list[str],
    sources: list[Sources],
    rules: tuple[str, ...] = BAND_RULES,
) -> dict[str, dict]:
    """The scores (``score_colours``) of the bank's views as the server renders them, by each of
    the band stage's ``rules``."""
    raw = render_raw(renderer, bank)
    return {
        rule: score_colours(bank, composite(bank, band_filled(bank, raw, sources, rule), raw[2]), names)
        for rule in rules
    }
