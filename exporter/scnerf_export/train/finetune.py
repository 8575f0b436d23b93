"""`scnerf-export finetune`: SC-NeRF's heads (M2, the two rectifiers, M4) trained on top of a frozen
backbone (G1, G2, M1), from the exact initialisation of ``init-scnerf``.

With G1, G2 and M1 frozen, everything the heads read for a ray (F_r, the point features f, the
appearance features, the ray direction, the sample depths) is fixed, so it is computed once into
a :class:`RayBank` and a training step costs only the heads: minutes per thousand steps on a CPU
instead of a volume build per step.

Training data are procedural scenes (photo-like ``tabletop`` and DTU-like ``object`` layouts at
DTU's 640x512, the resolution the backbone was trained at); per target, the 3 nearest views are
the sources. Validation scenes (``../shared/data``: lego, DTU scan37) only choose the checkpoint:
the step whose renders score best, never worse than the initialisation on any scene.
"""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from .. import cameras as cams
from ..data import datasets
from ..data.procedural import TRAIN_SEED0, load_scene, pick_sources
from ..data.procedural.dataset import build_dataset
from ..evaluate.eval import downscale_target, source_pool
from ..model.checkpoint import load_checkpoint, save_checkpoint
from ..model.network import SCNeRF
from ..model.renderer import RadiancePoints
from ..runtime.reference import encode_scene
from .from_scratch import hardware, psnr_from_mse

HEADS = ("m2", "geometry", "appearance", "colour_head")
RECTIFIERS = ("geometry", "appearance")
LAYOUTS = ("tabletop", "object")


@dataclass
class RayBank:
    """Per-ray inputs of the heads for many rays of many views, and the truth to compare with."""

    radiance: torch.Tensor  # F_r (N,S,C) float16
    point_features: torch.Tensor  # f (N,F,S) float16
    appearance: torch.Tensor  # mean [F_i, I_i] (N,A,S) float16
    ref_dir: torch.Tensor  # (N,3)
    z: torch.Tensor  # (N,S)
    depth_range: torch.Tensor  # (N,2)
    background: torch.Tensor  # (N,3)
    truth: torch.Tensor  # (N,3)
    view: torch.Tensor  # (N) index of the view each ray belongs to
    mask: torch.Tensor  # (N) bool: object pixel (DTU's mask), True where the view has none

    def __len__(self) -> int:
        return self.truth.shape[0]

    def storable(self) -> "RayBank":
        """The bank without rays whose F_r overflows float16 storage (a few rays of thousands, with
        trunk outputs beyond 65504): left in, they make every step that draws them NaN."""
        keep = torch.isfinite(self.radiance).flatten(1).all(dim=1)
        return RayBank(**{name: value[keep] for name, value in self.__dict__.items()})

    def points(self, idx: torch.Tensor) -> RadiancePoints:
        rays = idx.shape[0]

        def channels_first(x: torch.Tensor) -> torch.Tensor:  # (R,K,S) -> (K, R*S)
            return x[idx].float().transpose(0, 1).reshape(x.shape[1], -1)

        return RadiancePoints(
            self.z[idx],
            self.radiance[idx].float().reshape(rays * self.z.shape[1], -1),
            channels_first(self.point_features),
            channels_first(self.appearance),
            self.ref_dir[idx],
        )

    @staticmethod
    def concat(banks: list["RayBank"]) -> "RayBank":
        offsets = np.cumsum([0] + [int(b.view.max()) + 1 for b in banks[:-1]])
        fields = {name: torch.cat([getattr(b, name) for b in banks]) for name in RayBank.__dataclass_fields__}
        fields["view"] = torch.cat([b.view + int(o) for b, o in zip(banks, offsets)])
        return RayBank(**fields)


@torch.no_grad()
def bank_view(
    model: SCNeRF,
    sources: list,
    near: float,
    far: float,
    background,
    target_camera: cams.Camera,
    target_image: np.ndarray,
    pick: np.ndarray,
    mask: np.ndarray | None = None,
    chunk: int = 512,
) -> RayBank:
    """The heads' inputs for the pixels ``pick`` (flat indices) of one target view."""
    encoded = encode_scene(
        model, np.stack([v.image for v in sources]), [v.camera for v in sources], near, far, background
    )
    origins, directions = cams.target_rays(target_camera)
    near_far = torch.tensor([near, far], dtype=torch.float32)
    parts = []
    for start in range(0, len(pick), chunk):
        rows = pick[start : start + chunk]
        p = model.renderer.radiance_points(
            torch.from_numpy(origins[rows]),
            torch.from_numpy(directions[rows]),
            near_far,
            encoded.volume,
            encoded.images,
            encoded.features,
            encoded.intrinsics,
            encoded.extrinsics,
        )
        rays, samples = len(rows), p.z.shape[0]
        parts.append(
            (
                p.radiance.view(rays, samples, -1).half(),
                p.point_features.view(-1, rays, samples).transpose(0, 1).half(),
                p.appearance.view(-1, rays, samples).transpose(0, 1).half(),
                p.ref_dir,
                p.z,
            )
        )
    n = len(pick)
    return RayBank(
        radiance=torch.cat([q[0] for q in parts]),
        point_features=torch.cat([q[1] for q in parts]),
        appearance=torch.cat([q[2] for q in parts]),
        ref_dir=torch.cat([q[3] for q in parts]),
        z=parts[0][4][None, :].expand(n, -1).clone(),
        depth_range=torch.tensor([[near, far]], dtype=torch.float32).expand(n, -1).clone(),
        background=torch.tensor([background], dtype=torch.float32).expand(n, -1).clone(),
        truth=torch.from_numpy(target_image.reshape(-1, 3)[pick].astype(np.float32)),
        view=torch.zeros(n, dtype=torch.long),
        mask=torch.from_numpy(mask.reshape(-1)[pick]) if mask is not None else torch.ones(n, dtype=torch.bool),
    )


def shade(model: SCNeRF, bank: RayBank, idx: torch.Tensor) -> torch.Tensor:
    """Composited rgb of the rays ``idx`` through the heads (with gradients when enabled)."""
    rgb, _, opacity = model.renderer.shade(bank.points(idx), bank.depth_range[idx].transpose(0, 1))
    return rgb + (1.0 - opacity[:, None]) * bank.background[idx]


# ----------------------------------------------------------------------------------------------- data


def training_bank(
    model: SCNeRF,
    cache: Path,
    scenes: int,
    targets_per_scene: int,
    rays_per_target: int,
    seed: int,
    width: int = 640,
    height: int = 512,
    views: int = 12,
) -> RayBank:
    """Random rays of ``targets_per_scene`` targets in each of ``scenes`` procedural scenes (seeds
    from the training range), each target with its 3 nearest views as sources.

    Each target and its sources are composited on a random background (black, white or a random
    colour), as the server composites transparent photos: on black alone, empty space could take
    any opacity unpunished, and a white-background scene (lego) would pay for it."""
    paths = build_dataset(
        cache / "scenes", scenes, seed0=TRAIN_SEED0, layouts=LAYOUTS, n_views=views, width=width, height=height
    )
    rng = np.random.default_rng(seed)
    banks = []
    for path in tqdm(paths, desc="training rays", mininterval=10.0):
        scene = load_scene(path)
        for target in rng.choice(len(scene.views), size=targets_per_scene, replace=False):
            background = random_background(rng)
            sources = [on_background(scene.views[i], background) for i in pick_sources(scene, int(target), "small")]
            view = on_background(scene.views[int(target)], background)
            pick = rng.choice(width * height, size=rays_per_target, replace=False)
            banks.append(bank_view(model, sources, scene.near, scene.far, background, view.camera, view.image, pick))
    return RayBank.concat(banks)


def random_background(rng: np.random.Generator) -> tuple[float, float, float]:
    kind = rng.choice(["black", "white", "colour"], p=[0.5, 0.25, 0.25])
    colour = {"black": np.zeros(3), "white": np.ones(3), "colour": rng.uniform(0.0, 1.0, 3)}[kind]
    return tuple(float(c) for c in colour)


def on_background(view, background) -> datasets.View:
    """A procedural view (colour premultiplied by alpha: empty space is black) over ``background``."""
    image = view.image + (1.0 - view.alpha[..., None]) * np.asarray(background, dtype=np.float32)
    return datasets.View("", image.astype(np.float32), view.camera)


@dataclass(frozen=True)
class ValidationScene:
    """A real scene scored the paper's way: per target, the 3 nearest views of the source pool."""

    name: str
    path: str
    format: str
    target_scale: float
    stride: int  # every stride-th pixel of the (scaled) target along each axis


VALIDATION = (
    ValidationScene("lego", "nerf_synthetic_lego", "blender", 0.25, 2),
    ValidationScene("scan37", "dtu_scan37", "dtu", 0.5, 4),
)


def target_bank(
    model: SCNeRF, scene: datasets.SceneData, target: str, sources: list[str], target_scale: float, stride: int
) -> RayBank:
    """The heads' inputs for every ``stride``-th pixel along each axis of ``target`` at
    ``target_scale``, rendered from the views ``sources``."""
    view = downscale_target(scene.views[target], target_scale)
    grid = np.zeros(view.image.shape[:2], dtype=bool)
    grid[::stride, ::stride] = True
    views = datasets.get_views(scene, list(sources))
    pick = np.flatnonzero(grid)
    return bank_view(model, views, scene.near, scene.far, scene.background, view.camera, view.image, pick, view.mask)


def validation_bank(model: SCNeRF, shared: Path, spec: ValidationScene) -> RayBank:
    scene = datasets.load_scene(shared / "data" / spec.path, spec.format)
    pool = source_pool(scene, scene.default_targets)
    return RayBank.concat(
        [
            target_bank(model, scene, name, datasets.nearest_sources(scene, name, pool), spec.target_scale, spec.stride)
            for name in scene.default_targets
        ]
    )


def backbone_digest(model: SCNeRF) -> str:
    """Names the frozen weights (G1, G2, M1) a bank was computed with."""
    h = hashlib.sha256()
    for key, tensor in sorted(model.state_dict().items()):
        if key.startswith(("encoder.", "volume_net.", "renderer.m1.")):
            h.update(key.encode())
            h.update(tensor.numpy().tobytes())
    return h.hexdigest()[:12]


def cached(path: Path, build) -> RayBank:
    """A bank read from ``path`` if an earlier run wrote it, else built and written there."""
    if path.is_file():
        return RayBank(**torch.load(path, weights_only=True)).storable()
    bank = build().storable()
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(bank.__dict__, path.with_suffix(".tmp"))
    path.with_suffix(".tmp").replace(path)
    return bank


@torch.no_grad()
def score(model: SCNeRF, bank: RayBank, chunk: int = 2048) -> dict[str, float]:
    """Mean over views of the PSNR of the banked pixels, and of the object pixels where masked."""
    rgb = torch.cat(
        [shade(model, bank, torch.arange(s, min(s + chunk, len(bank)))) for s in range(0, len(bank), chunk)]
    ).clamp(0.0, 1.0)
    error = ((rgb - bank.truth) ** 2).mean(dim=1)
    full, masked = [], []
    for v in range(int(bank.view.max()) + 1):
        rows = bank.view == v
        full.append(psnr_from_mse(float(error[rows].mean())))
        if not bool(bank.mask[rows].all()):
            masked.append(psnr_from_mse(float(error[rows & bank.mask].mean())))
    out = {"psnr": float(np.mean(full))}
    if masked:
        out["psnr_masked"] = float(np.mean(masked))
    return out


# ------------------------------------------------------------------------------------------- training


@dataclass(frozen=True)
class Recipe:
    steps: int = 1500
    rays: int = 512
    lr: float = 2e-4  # the rectifiers, which start at zero output
    pretrained_lr_scale: float = 0.1  # M2 and M4 start from MVSNeRF's trained heads: smaller steps
    scenes: int = 40
    targets_per_scene: int = 3
    rays_per_target: int = 512
    validate_every: int = 300
    seed: int = 0


def finetune(
    init: str | Path,
    out_dir: str | Path,
    shared: str | Path,
    recipe: Recipe = Recipe(),
    threads: int | None = None,
    cache_dir: str | Path | None = None,
) -> Path:
    """Train the heads of the ``init`` checkpoint on procedural scenes, chosen on the validation
    scenes of ``shared`` (:func:`train_heads`), and write ``best.pt``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if threads:
        torch.set_num_threads(threads)
    torch.manual_seed(recipe.seed)
    model, provenance = load_checkpoint(init)
    if model.cfg.variant != "scnerf":
        raise ValueError(f"{init}: finetune trains scnerf's heads, got a {model.cfg.variant} network")
    model.eval()

    start = time.perf_counter()
    cache = Path(cache_dir) if cache_dir else out / "cache"
    backbone = backbone_digest(model)
    train_bank = cached(
        cache / f"train-{backbone}-{recipe.scenes}x{recipe.targets_per_scene}x"
        f"{recipe.rays_per_target}-seed{recipe.seed}-bg.pt",
        lambda: training_bank(
            model, cache, recipe.scenes, recipe.targets_per_scene, recipe.rays_per_target, recipe.seed
        ),
    )
    val_banks = {
        spec.name: cached(
            cache / f"val-{backbone}-{spec.name}-{spec.target_scale}-{spec.stride}.pt",
            lambda spec=spec: validation_bank(model, Path(shared), spec),
        )
        for spec in VALIDATION
    }
    about = {
        "data": f"procedural scenes (scnerf_export.data.procedural, layouts {', '.join(LAYOUTS)}), "
        f"{recipe.scenes} scenes of the training seed range at 640x512, {recipe.targets_per_scene} "
        f"targets each with their 3 nearest views, {recipe.rays_per_target} random rays per target, "
        "each target on a random black, white or coloured background",
        "ray_bank_seconds": time.perf_counter() - start,
        "validation_scenes": [spec.__dict__ for spec in VALIDATION],
    }
    return train_heads(model, train_bank, val_banks, recipe, out, about, provenance.get("derived_from"))


def head_parameter_groups(model: SCNeRF, recipe: Recipe) -> list[dict]:
    """The heads' parameters with their learning rates; every other parameter frozen."""
    for p in model.parameters():
        p.requires_grad_(False)
    groups = [
        {
            "params": list(getattr(model.renderer, name).parameters()),
            "lr": recipe.lr * (1.0 if name in RECTIFIERS else recipe.pretrained_lr_scale),
        }
        for name in HEADS
    ]
    for group in groups:
        for p in group["params"]:
            p.requires_grad_(True)
    return groups


def heads_step(model: SCNeRF, optimiser: torch.optim.Optimizer, bank: RayBank, idx: torch.Tensor) -> float:
    """One optimiser step on the rays ``idx`` of ``bank``; the loss before it."""
    loss = torch.mean((shade(model, bank, idx) - bank.truth[idx]) ** 2)
    optimiser.zero_grad(set_to_none=True)
    loss.backward()
    optimiser.step()
    return float(loss.detach())


def train_heads(
    model: SCNeRF,
    train_bank: RayBank,
    val_banks: dict[str, RayBank],
    recipe: Recipe,
    out: Path,
    about: dict,
    derived_from: dict | None,
) -> Path:
    """Train the heads on ``train_bank`` and write ``out/best.pt``: among the validated steps (every
    ``recipe.validate_every`` and the last), the one with the best mean PSNR gain over the
    initialisation on ``val_banks``, no worse than it on any of them (step 0 if none).

    ``about``: what the checkpoint's training record says of the training rays (``data``, how long
    they took, ``ray_bank_seconds``) and of the validation banks (``validation_scenes``)."""
    model.eval()
    groups = head_parameter_groups(model, recipe)
    log = open(out / "log.jsonl", "a")

    def validate(step: int) -> dict:
        scores = {name: score(model, bank) for name, bank in val_banks.items()}
        flat = {f"{name}_{k}": v for name, s in scores.items() for k, v in s.items()}
        log.write(json.dumps({"step": step, "validation": flat}) + "\n")
        log.flush()
        return flat

    def training_record(best_step: int, chosen: dict) -> dict:
        return {
            "what": "M2, the geometry and appearance rectifiers and M4 trained on top of the exact MVSNeRF "
            "initialisation; G1, G2 and M1 frozen",
            "data": about["data"],
            "recipe": recipe.__dict__,
            "steps": best_step,
            "seed": recipe.seed,
            "hardware": hardware(),
            "seconds": seconds,
            "ray_bank_seconds": about["ray_bank_seconds"],
            "selection": {
                "rule": "validated step with the best mean PSNR gain over the initialisation, no worse "
                "than it on any validation scene (validation scenes choose, never train)",
                "scenes": about["validation_scenes"],
                "initial": initial,
                "chosen": chosen,
            },
        }

    # best.pt is written whenever a validated step becomes the best, so an interrupted run keeps it.
    path = out / "best.pt"
    seconds, best_gain = 0.0, 0.0
    initial = validate(0)
    save_checkpoint(path, model, {"derived_from": derived_from, "training": training_record(0, initial)})
    optimiser = torch.optim.Adam(groups)
    rng = torch.Generator().manual_seed(recipe.seed)
    bar = tqdm(range(recipe.steps), desc="finetune", mininterval=10.0, dynamic_ncols=True)
    for step in bar:
        tick = time.perf_counter()
        idx = torch.randint(len(train_bank), (recipe.rays,), generator=rng)
        value = heads_step(model, optimiser, train_bank, idx)
        seconds += time.perf_counter() - tick
        bar.set_postfix(loss=f"{value:.5f}")
        log.write(json.dumps({"step": step + 1, "loss": value, "seconds": seconds}) + "\n")
        log.flush()
        if (step + 1) % recipe.validate_every == 0 or step + 1 == recipe.steps:
            scores = validate(step + 1)
            gains = [scores[k] - initial[k] for k in initial]
            print(
                f"step {step + 1}: " + ", ".join(f"{k} {v:.3f} ({v - initial[k]:+.3f})" for k, v in scores.items()),
                flush=True,
            )
            if min(gains) >= 0.0 and float(np.mean(gains)) > best_gain:
                best_gain = float(np.mean(gains))
                save_checkpoint(
                    path, model, {"derived_from": derived_from, "training": training_record(step + 1, scores)}
                )
    log.close()
    return path
