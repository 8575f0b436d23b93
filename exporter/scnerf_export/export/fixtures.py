"""Parity fixtures for the Rust tests: a random-weight small bundle, requests and the PyTorch
reference outputs, and beside them the same bundle's volume graphs for the slab-by-slab and the
plane-sweep builds (docs/bundle.md "Parity fixtures")."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from .. import cameras as cams
from ..cameras import Camera, camera_from_json, camera_json
from ..config import small_config
from ..model.network import SCNeRF
from ..rigs import random_model, rig_cameras, smooth_pattern
from ..runtime.band import Sources, fill_from_sources, sightings, surface_points
from ..runtime.reference import encode_scene, render_target, render_view
from .bundle import export_bundle
from .split_volume import split_volume_bundle

# The manifests' time of creation: fixed, so that the generator writes the committed files again
# byte for byte.
CREATED = "2026-12-07T00:00:00+00:00"
SPLIT_BUILDS = ("slabs", "sweep")


def _write_f32(path: Path, array) -> None:
    np.ascontiguousarray(np.asarray(array, dtype="<f4")).tofile(path)


def write_case(
    out: Path,
    model: SCNeRF,
    name: str,
    height: int,
    width: int,
    target_scale: float,
    style: str,
    background: tuple[float, float, float],
    seed: int,
) -> None:
    rng = np.random.default_rng(seed)
    sources, target, near, far = rig_cameras(height, width)
    target = target.scaled(target_scale)
    case = out / name
    case.mkdir(parents=True, exist_ok=True)
    images = []
    for i in range(len(sources)):
        rgba = (smooth_pattern(rng, height, width) * 255).round().astype(np.uint8)
        Image.fromarray(rgba).save(case / f"source_{i}.png")
        images.append(np.asarray(Image.open(case / f"source_{i}.png"), dtype=np.float32) / 255.0)
    images = np.stack(images)
    request = {
        "sources": [{"camera": camera_json(c, style)} for c in sources],
        "target": camera_json(target, style),
        "near": near,
        "far": far,
        "background": list(background),
        "outputs": ["rgb", "depth", "opacity"],
    }
    (case / "request.json").write_text(json.dumps(request, indent=2) + "\n")
    # Decode the request the way the server does, so the fixture tests the conversions too.
    parsed = [camera_from_json(s["camera"]) for s in request["sources"]]
    parsed_target = camera_from_json(request["target"])
    result = render_view(model, images, parsed, parsed_target, near, far, background, chunk=97)
    with torch.no_grad():
        scene = encode_scene(model, images, parsed, near, far, background)
    guided = render_target(model, scene, parsed_target, near, far, background, chunk=97, sampling="guided")
    for name in ("rgb", "depth", "opacity"):
        _write_f32(case / f"{name}_guided.f32", getattr(guided, name))
    _write_f32(case / "rgb.f32", result.rgb)
    _write_f32(case / "depth.f32", result.depth)
    _write_f32(case / "opacity.f32", result.opacity)
    _write_f32(case / "features.f32", scene.features.numpy())
    _write_f32(case / "volume.f32", scene.volume.numpy())
    expected = {
        "width": parsed_target.width,
        "height": parsed_target.height,
        "background": list(background),
        "files": {
            "rgb": "rgb.f32",
            "depth": "depth.f32",
            "opacity": "opacity.f32",
            "features": "features.f32",
            "volume": "volume.f32",
            "rgb_guided": "rgb_guided.f32",
            "depth_guided": "depth_guided.f32",
            "opacity_guided": "opacity_guided.f32",
        },
        "shapes": {
            "rgb": [parsed_target.height, parsed_target.width, 3],
            "depth": [parsed_target.height, parsed_target.width],
            "opacity": [parsed_target.height, parsed_target.width],
            "features": list(scene.features.shape),
            "volume": list(scene.volume.shape),
            "rgb_guided": [parsed_target.height, parsed_target.width, 3],
            "depth_guided": [parsed_target.height, parsed_target.width],
            "opacity_guided": [parsed_target.height, parsed_target.width],
        },
        # Guided sampling (the bundle's policy): the same view, its network samples per pixel and
        # how many pixels took each path (what the case exercises).
        "guided_samples_per_ray": guided.samples_per_ray,
        "guided_paths": guided.paths,
        "tolerances": {
            "rgb_max_abs": 1e-3,
            "depth_max_rel": 1e-3,
            "opacity_max_abs": 1e-3,
            "features_max_abs": 1e-4,
            "volume_max_abs": 1e-4,
        },
        "stats": {"opacity_mean": float(result.opacity.mean()), "rgb_std": float(result.rgb.std())},
    }
    (case / "expected.json").write_text(json.dumps(expected, indent=2) + "\n")


def write_band_case(out: Path, seed: int) -> None:
    """``band.json``: the band's recolouring (runtime/band.py) of a random raw view of the rig's
    target (its field of view widened, so that some pixels lie outside every source), its band at
    half the brightness of the rest, from its three sources padded to 32 rows, for
    server/src/pipeline/band.rs."""
    rng = np.random.default_rng(seed)
    sources, target, near, far = rig_cameras(24, 32)
    target = target.scaled(0.5)
    target = Camera(target.K @ np.diag([0.6, 0.6, 1.0]), target.w2c, target.width, target.height)
    images = np.stack([smooth_pattern(rng, 24, 32) for _ in sources]).transpose(0, 3, 1, 2)
    padded = np.zeros((3, 3, 32, 32), np.float32)
    padded[:, :, :24] = images
    n = target.width * target.height
    opacity = rng.uniform(0, 1, n).astype(np.float32)
    raw = {
        "rgb": (rng.uniform(0, 1, (n, 3)) * opacity[:, None]).astype(np.float32),
        "depth": rng.uniform(near - 0.5, far + 2.0, n).astype(np.float32),
        "opacity": opacity,
    }
    scene = {
        "images": padded,
        "source_sizes": [(c.width, c.height) for c in sources],
        "intrinsics": cams.stack_intrinsics(sources),
        "extrinsics": cams.stack_extrinsics(sources),
    }
    origins, directions = cams.target_rays(target)
    band_sources = Sources.of(scene)
    views, *_ = sightings(surface_points(raw["depth"], origins, directions), band_sources)
    raw["rgb"][(views > 0) & (views < 3)] *= 0.5
    filled, band = fill_from_sources(raw["rgb"], raw["depth"], opacity, origins, directions, band_sources)
    case = {
        "seed": seed,
        "target": camera_json(target),
        **{k: np.asarray(v).tolist() for k, v in scene.items()},
        "raw": {k: v.tolist() for k, v in raw.items()},
        "expected_rgb": filled.tolist(),
        "band_pixels": int(band.sum()),
    }
    (out / "band.json").write_text(json.dumps(case) + "\n")


def split_siblings(out_dir: str | Path) -> dict[str, Path]:
    """The folders beside ``out_dir`` that hold its bundle's volume graphs for each split build
    (``parity`` -> ``parity-slabs``, ``parity-sweep``)."""
    out = Path(out_dir)
    return {build: out.with_name(f"{out.name}-{build}") for build in SPLIT_BUILDS}


def write_split(bundle: Path, model: SCNeRF, build: str, out: Path) -> None:
    """``bundle``'s volume graphs for ``build``, written from ``model`` (the bundle's network) with
    their manifest into ``out``; the graphs that ``bundle`` holds unchanged are left out (the tests
    take them from the bundle)."""
    manifest = split_volume_bundle(bundle, out, build, model=model)
    for entry in manifest.graphs.values():
        if (bundle / entry.file).is_file():
            (out / entry.file).unlink()


def write_fixtures(out_dir: str | Path, variant: str = "scnerf", seed: int = 7) -> list[Path]:
    """Writes the parity fixtures into ``out_dir`` and the split volume graphs into its siblings
    (``split_siblings``); the folders written."""
    out = Path(out_dir)
    model = random_model(small_config(variant), seed)
    export_bundle(
        model,
        out / "bundle",
        {
            "source_checkpoint": None,
            "source_kind": "random-weights",
            "training": f"random weights, torch seed {seed} (test fixture only)",
        },
        created=CREATED,
    )
    siblings = split_siblings(out)
    for build, sibling in siblings.items():
        write_split(out / "bundle", model, build, sibling)
    cases = out / "cases"
    write_case(cases, model, "opencv_64x96", 64, 96, 1.0, "opencv_w2c", (0.0, 0.0, 0.0), seed + 1)
    write_case(cases, model, "opengl_96x64_white", 96, 64, 0.75, "opengl_c2w", (1.0, 1.0, 1.0), seed + 2)
    write_band_case(out, seed + 3)
    (out / "READY").write_text("fixtures complete\n")
    return [out, *siblings.values()]
