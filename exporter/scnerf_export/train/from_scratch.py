"""Training on procedural scenes (paper Sec. 3.3): 3 nearby source views, random target rays,
L2 loss on colour, Adam 5e-4. Checkpoints often and resumes, so it can run in the background."""

from __future__ import annotations

import json
import os
import platform
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from PIL import Image
from tqdm import tqdm

from .. import cameras as cams
from ..config import ModelConfig
from ..data.procedural import ProceduralDataset
from ..model.checkpoint import save_checkpoint
from ..model.network import SCNeRF
from ..runtime.reference import render_view


@dataclass(frozen=True)
class Preset:
    """Sizes of one training recipe; written into the checkpoint and the bundle's provenance."""

    name: str
    config: ModelConfig
    width: int
    height: int
    rays: int
    steps: int
    train_scenes: int
    gaps: tuple[str, ...] = ("small", "medium")
    checkpoint_every: int = 100
    validate_every: int = 500
    lr: float = 5e-4
    views: int = 20  # per procedural scene
    validation_scenes: int = 3


def preset(name: str, variant: str) -> Preset:
    if name == "cpu-small":
        # The paper's network shrunk to train on one CPU core in about an hour: width 64, 48 planes and
        # samples, 384 rays per step (measured ~1.1 s of CPU per scnerf step, ~0.6 s per mvsnerf step).
        cfg = ModelConfig(variant=variant, width=64, depth_planes=48, samples=48, pad=8, colour_hidden=32)
        return Preset(name, cfg, width=160, height=128, rays=384, steps=3000, train_scenes=96)
    if name == "gpu":
        cfg = ModelConfig(variant=variant)
        return Preset(
            name,
            cfg,
            width=320,
            height=256,
            rays=1024,
            steps=20000,
            train_scenes=600,
            checkpoint_every=250,
            validate_every=1000,
        )
    raise ValueError(f"unknown preset {name!r} (cpu-small, gpu)")


def to_tensors(example, device):
    images = np.stack([v.image for v in example.sources]).transpose(0, 3, 1, 2)
    cameras = [v.camera for v in example.sources]
    t = lambda a: torch.from_numpy(np.ascontiguousarray(a)).to(device)  # noqa: E731
    return {
        "images": t(images),
        "projections": t(cams.feature_projections(cameras)),
        "intrinsics": t(cams.stack_intrinsics(cameras)),
        "extrinsics": t(cams.stack_extrinsics(cameras)),
        "near_far": torch.tensor([example.near, example.far], dtype=torch.float32, device=device),
    }


def training_loss(model: SCNeRF, example, rays: int, rng: np.random.Generator, device) -> torch.Tensor:
    """Loss L = ||rgb - rgb_hat||^2 on ``rays`` random pixels of the target (paper Eq. 15)."""
    x = to_tensors(example, device)
    planes = torch.from_numpy(cams.depth_planes(example.near, example.far, model.cfg.depth_planes)).to(device)
    features = model.encode(x["images"])
    volume = model.build_volume(features, x["images"], x["projections"], planes)
    origins, directions = cams.target_rays(example.target.camera)
    pick = rng.choice(origins.shape[0], size=rays, replace=False)
    gt = torch.from_numpy(example.target.image.reshape(-1, 3)[pick]).to(device)
    rgb, _, _ = model.renderer(
        torch.from_numpy(origins[pick]).to(device),
        torch.from_numpy(directions[pick]).to(device),
        x["near_far"],
        x["near_far"],
        volume,
        x["images"],
        features,
        x["intrinsics"],
        x["extrinsics"],
    )
    return torch.mean((rgb - gt) ** 2)


def training_step(
    model: SCNeRF, optimiser: torch.optim.Optimizer, example, rays: int, rng: np.random.Generator, device
) -> float:
    """One optimiser step on ``rays`` random pixels of the example's target; the loss before it."""
    loss = training_loss(model, example, rays, rng, device)
    optimiser.zero_grad(set_to_none=True)
    loss.backward()
    optimiser.step()
    return float(loss.detach())


def psnr_from_mse(mse: float) -> float:
    return float(-10.0 * np.log10(max(mse, 1e-12)))


def validate(model: SCNeRF, examples, out_dir: Path, step: int) -> dict:
    """Full renders of fixed held-out examples; writes one PNG strip (render | truth) per example."""
    model.eval()
    scores = {}
    for i, ex in enumerate(examples):
        images = np.stack([v.image for v in ex.sources])
        result = render_view(
            model.cpu(), images, [v.camera for v in ex.sources], ex.target.camera, ex.near, ex.far, chunk=2048
        )
        mse = float(np.mean((result.rgb - ex.target.image) ** 2))
        scores[f"{ex.layout}_{i}"] = psnr_from_mse(mse)
        strip = np.concatenate([np.clip(result.rgb, 0, 1), ex.target.image], axis=1)
        Image.fromarray((strip * 255).round().astype(np.uint8)).save(out_dir / f"val_{step:06d}_{i}.png")
    model.train()
    return scores


def hardware() -> str:
    if torch.cuda.is_available():
        return f"CUDA {torch.cuda.get_device_name(0)}"
    model = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            model = next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    return f"CPU {model}, {torch.get_num_threads()} threads of {os.cpu_count()}"


def train(
    p: Preset,
    out_dir: str | Path,
    resume: bool = False,
    steps: int | None = None,
    seed: int = 0,
    cache_dir: str | Path | None = None,
    threads: int | None = None,
) -> Path:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if threads:
        torch.set_num_threads(threads)
    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    total = steps or p.steps
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    model = SCNeRF(p.config).to(device).train()
    optimiser = torch.optim.Adam(model.parameters(), lr=p.lr)
    start, seconds = 0, 0.0
    last = out / "last.pt"
    if resume and last.exists():
        state = torch.load(last, map_location=device, weights_only=False)
        model.load_state_dict(state["state_dict"])
        optimiser.load_state_dict(state["optimizer"])
        rng.bit_generator.state = state["rng"]
        torch.set_rng_state(state["torch_rng"])
        start, seconds = state["step"], state["training"]["seconds"]

    cache = Path(cache_dir) if cache_dir else out / "cache"
    train_set = ProceduralDataset(
        "train",
        n_scenes=p.train_scenes,
        n_views=p.views,
        width=p.width,
        height=p.height,
        gaps=p.gaps,
        cache_dir=cache / "train",
        seed=seed,
    )
    val_set = ProceduralDataset(
        "val",
        n_scenes=p.validation_scenes,
        n_views=p.views,
        width=p.width,
        height=p.height,
        gaps=("small",),
        cache_dir=cache / "val",
        seed=seed,
    )
    val_examples = list(val_set.fixed_examples(targets_per_scene=1))
    log = open(out / "log.jsonl", "a")

    def training_record(step: int) -> dict:
        return {
            "preset": p.name,
            "variant": p.config.variant,
            "steps": step,
            "data_seed": seed,
            "train_scenes": p.train_scenes,
            "image_size": [p.width, p.height],
            "rays_per_step": p.rays,
            "gaps": list(p.gaps),
            "lr": p.lr,
            "hardware": hardware(),
            "seconds": seconds,
            "data": "procedural scenes (scnerf_export.data.procedural), object/forward/outdoor layouts",
        }

    def save(step: int) -> None:
        tmp = out / "last.pt.tmp"
        save_checkpoint(
            tmp,
            model,
            {
                "training": training_record(step),
                "optimizer": optimiser.state_dict(),
                "rng": rng.bit_generator.state,
                "torch_rng": torch.get_rng_state(),
                "step": step,
            },
        )
        os.replace(tmp, last)

    bar = tqdm(
        range(start, total),
        initial=start,
        total=total,
        desc=f"{p.config.variant}/{p.name}",
        mininterval=5.0,
        dynamic_ncols=True,
    )
    for step in bar:
        tick = time.perf_counter()
        value = training_step(model, optimiser, train_set.sample(rng), p.rays, rng, device)
        elapsed = time.perf_counter() - tick
        seconds += elapsed
        bar.set_postfix(loss=f"{value:.4f}", psnr=f"{psnr_from_mse(value):.2f}", rays_s=f"{p.rays / elapsed:.0f}")
        record = {"step": step + 1, "loss": value, "psnr": psnr_from_mse(value), "seconds": seconds}
        if (step + 1) % p.validate_every == 0 or step + 1 == total:
            record["val_psnr"] = validate(model, val_examples, out, step + 1)
            model.to(device)
        log.write(json.dumps(record) + "\n")
        log.flush()
        if (step + 1) % p.checkpoint_every == 0 or step + 1 == total:
            save(step + 1)
    log.close()
    return last
