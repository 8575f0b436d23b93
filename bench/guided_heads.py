"""`python -m bench.guided_heads`: what a ray of guided sampling loses by reading the rectifier
heads of its guide ray, against the alternatives, on real scenes.

Guided sampling (runtime/guided.py) renders most pixels at K of the S uniform samples. The
rectifiers attend along the sample axis, so such a pixel reads the attention heads of the nearest
level-0 ray, computed there from all S samples. Per scene (as bench.sampling: lego r_28 and scan37
view 32, each from its 3 nearest source views; the sources encoded by the bundle's graphs in ONNX
Runtime, the renderer in PyTorch with its weights read back from renderer.onnx) the view is
rendered in full (every pixel at all S samples with its own heads), then by the guided policy as
shipped. Every pixel the policy renders at K samples is rendered again, with the same samples and
multiplicities, by each variant of what its rectifiers read:

* ``guide``: the heads of the nearest level-0 ray (what the server does);
* ``own-K``: its own heads from its K samples alone (:func:`heads_over_samples`);
* ``own-S``: its own heads from all S samples (an oracle: it needs the full render);
* ``none``: no rectification.

Each is compared with the full render on those pixels, composited on the scene's background (PSNR
and max abs difference), over all of them and per level, and with the ground truth. Writes
``bench/results/guided-heads-<date>.json`` and prints markdown tables.

    PYTHONPATH=exporter:. .venv/bin/python -m bench.guided_heads
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import math
import os
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from scnerf_export import cameras as cams
from scnerf_export.data import datasets
from scnerf_export.evaluate import metrics
from scnerf_export.evaluate.eval import source_pool
from scnerf_export.export.manifest import Manifest
from scnerf_export.export.reexport import renderer_state_from_current_graph
from scnerf_export.model.network import SCNeRF
from scnerf_export.model.rectifiers import SampleAxisAttention
from scnerf_export.model.renderer import RayRenderer, Shading, composite_weights
from scnerf_export.runtime.guided import render_guided
from scnerf_export.runtime.onnx_pipeline import OnnxBundle
from scnerf_export.runtime.reference import SceneTensors

from .sampling import SCENES, SHARED, cpu_name, cropped_target, write_results
from .scene import parse_sizes

VARIANTS = ("guide", "own-K", "own-S", "none")
# Not a variant but the scale of them all: the same pixels at all S samples, unrectified.
UNRECTIFIED = "none-S"
ORACLE = "own-S"
OUTPUTS = ("rgb", "depth", "opacity", "weights")
# What a rectifier reads at K samples: (name, rectifier, query, keys (K_in,R,K), values (R,K,C)) ->
# heads (R, h*d_k, C), or None to leave the features unrectified.
HeadsOf = Callable[[str, SampleAxisAttention, torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor | None]


def heads_over_samples(
    rectifier: SampleAxisAttention, query: torch.Tensor, keys: torch.Tensor, values: torch.Tensor, index: torch.Tensor
) -> torch.Tensor:
    """Multihead(Q, K, V) of a ray from its K samples alone: the projections along S read only the
    columns of the samples present (the others count as absent, not as zero features). Q stays the
    ray's, constant along the samples, as in the model (a bundle keeps W_q only through its row
    sums, so a Q of fewer samples cannot be rebuilt). query (R,Q_in), keys (K_in,R,K), values
    (R,K,C), index (R,K) -> (R, h*d_k, C), W_v's bias left to the output as in ``summary``."""
    rays, _, channels = values.shape
    heads, dk = rectifier.heads, rectifier.head_dim
    columns = index.long()
    q = rectifier.query_m3(query)[..., None] * rectifier.w_q.weight.sum(dim=1) + rectifier.w_q.bias
    embedded = rectifier.key_embedding(keys.permute(1, 2, 0))  # (R,K,C)
    k = embedded.transpose(1, 2) @ rectifier.w_k.weight.t()[columns] + rectifier.w_k.bias
    v = values.transpose(1, 2) @ rectifier.w_v.weight.t()[columns]
    q, k, v = (t.view(rays, channels, heads, dk).transpose(1, 2) for t in (q, k, v))  # (R,h,C,d_k)
    attention = torch.softmax(q @ k.transpose(-1, -2) / math.sqrt(dk), dim=-1)
    return (attention @ v).transpose(-1, -2).reshape(rays, heads * dk, channels)


def render_at_samples(
    renderer: RayRenderer,
    scene: SceneTensors,
    near_far: torch.Tensor,
    origins: torch.Tensor,
    directions: torch.Tensor,
    index: torch.Tensor,
    multiplicity: torch.Tensor,
    heads_of: HeadsOf,
) -> Shading:
    """``renderer.render_samples`` with the rectifiers reading what ``heads_of`` gives."""
    step = (near_far[1] - near_far[0]) / (renderer.cfg.samples - 1)
    tensors = (scene.volume, scene.images, scene.features, scene.intrinsics, scene.extrinsics)
    points = renderer.radiance_points(origins, directions, near_far, *tensors, near_far[0] + index * step)
    rays, count = index.shape
    weights = composite_weights(renderer.m2(points.radiance).view(rays, count) * multiplicity)
    depth, opacity = renderer._depth_and_opacity(points.z, weights)
    radiance = points.radiance.view(rays, count, -1)
    query = renderer._query(depth, near_far, points.ref_dir)
    for name, rectifier in renderer.rectifiers().items():
        heads = heads_of(name, rectifier, query, renderer._keys(points, name, rays, count), radiance)
        if heads is not None:
            radiance = rectifier.correct(radiance, heads, index)
    return Shading(renderer._composite(radiance, query, points.ref_dir, weights), depth, opacity, weights, {})


def no_heads(*_) -> None:
    return None


def render_variants(
    renderer: RayRenderer,
    scene: SceneTensors,
    near_far: torch.Tensor,
    origins: torch.Tensor,
    directions: torch.Tensor,
    index: torch.Tensor,
    multiplicity: torch.Tensor,
    guide_heads: dict[str, torch.Tensor],
    own_heads: dict[str, torch.Tensor],
) -> dict[str, Shading]:
    """Rays at the samples ``index`` (R,K) with ``multiplicity``, once per variant (VARIANTS):
    rectified with ``guide_heads``, with their heads from the K samples, with ``own_heads`` (their
    own from all S), and unrectified. Heads per rectifier, (R, h*d_k, C)."""

    def given(heads: dict[str, torch.Tensor]) -> HeadsOf:
        return lambda name, *_: heads[name]

    def from_samples(name, rectifier, query, keys, values):
        return heads_over_samples(rectifier, query, keys, values, index)

    choices = {"guide": given(guide_heads), "own-K": from_samples, "own-S": given(own_heads), "none": no_heads}
    args = (renderer, scene, near_far, origins, directions, index, multiplicity)
    return {variant: render_at_samples(*args, choices[variant]) for variant in VARIANTS}


def load_renderer(bundle_dir: Path) -> RayRenderer:
    """The bundle's renderer in PyTorch, its weights read back from renderer.onnx."""
    manifest = Manifest.load(bundle_dir)
    model = SCNeRF(manifest.config).eval()
    state = renderer_state_from_current_graph(manifest.graph_path(bundle_dir, "renderer"), model)
    model.renderer.load_state_dict(state)
    return model.renderer


def render_full(renderer: RayRenderer, scene: SceneTensors, near_far, origins, directions, chunk: int) -> dict:
    """Every ray at all S samples: rgb, depth, opacity, weights (numpy) and per rectifier its heads."""
    tensors = (scene.volume, scene.images, scene.features, scene.intrinsics, scene.extrinsics)
    parts = []
    for start in range(0, len(origins), chunk):
        o, d = (torch.from_numpy(np.ascontiguousarray(a[start : start + chunk])) for a in (origins, directions))
        parts.append(renderer.guide(o, d, near_far, near_far, *tensors))
    full = {k: torch.cat([getattr(p, k) for p in parts]).numpy() for k in ("rgb", "depth", "opacity", "weights")}
    full["heads"] = {name: torch.cat([p.heads[name] for p in parts]) for name in renderer.rectifiers()}
    return full


def fine_levels(renderer, scene, near_far, policy, camera, background, full: dict, chunk: int) -> tuple[list, object]:
    """The guided policy as shipped over the view, its level-0 pixels taken from ``full``, every
    pixel it renders at K samples rendered by each variant (the ``guide`` one carries the policy
    on). Returns per level its pixels (rows of the view), K and each variant's rgb and opacity; and
    the policy's view (``GuidedView``)."""
    origins, directions = cams.target_rays(camera)
    samples = renderer.cfg.samples
    # The policy hands its callbacks rays, not pixels: a pixel is found by its unique direction.
    row_of = {d.tobytes(): i for i, d in enumerate(directions)}
    level0, levels = [], []

    def rows_of(dirs: np.ndarray) -> np.ndarray:
        return np.array([row_of[d.tobytes()] for d in dirs])

    def full_at(rows: np.ndarray) -> dict:
        return {k: full[k][rows] for k in ("rgb", "depth", "opacity", "weights")}

    def guide(_, dirs):
        level0.append(rows_of(dirs))
        return full_at(level0[0])

    def fine(_, dirs, index, multiplicity, guide_rows):
        rows = rows_of(dirs)
        guides = level0[0][guide_rows.astype(np.int64)]
        parts = {v: [] for v in VARIANTS + (UNRECTIFIED,)}
        for start in range(0, len(rows), chunk):
            run = slice(start, start + chunk)
            o, d, i, m = (torch.from_numpy(a[run]) for a in (origins[rows], dirs, index, multiplicity))
            guide_heads = {n: h[guides[run]] for n, h in full["heads"].items()}
            own_heads = {n: h[rows[run]] for n, h in full["heads"].items()}
            for v, s in render_variants(renderer, scene, near_far, o, d, i, m, guide_heads, own_heads).items():
                parts[v].append(s)
            every = torch.arange(samples, dtype=torch.float32).expand(len(o), samples)
            unrectified = render_at_samples(renderer, scene, near_far, o, d, every, torch.ones_like(every), no_heads)
            parts[UNRECTIFIED].append(unrectified)
        shaded = {v: {k: torch.cat([getattr(s, k) for s in p]).numpy() for k in OUTPUTS} for v, p in parts.items()}
        levels.append({"rows": rows, "samples": index.shape[1], "variants": shaded})
        return shaded["guide"]

    view = render_guided(policy, camera.width, camera.height, samples, origins, directions, background, guide, fine)
    return levels, view


def composited(rgb: np.ndarray, opacity: np.ndarray, background: np.ndarray) -> np.ndarray:
    return rgb + (1.0 - opacity[:, None]) * background


def agreement(colours: np.ndarray, reference: np.ndarray) -> dict:
    return {"psnr": metrics.psnr(colours, reference), "max_abs": float(np.abs(colours - reference).max())}


def variant_colours(levels: list, variant: str, background: np.ndarray) -> np.ndarray:
    shaded = [level["variants"][variant] for level in levels]
    return np.concatenate([composited(s["rgb"], s["opacity"], background) for s in shaded])


def scores(levels: list, full: dict, truth: np.ndarray, background: np.ndarray) -> dict:
    """Over each level's pixels and all of them: each variant against the full render, the oracle
    (own-S: what the heads alone cost) and the ground truth; the full render against the truth."""
    reference = composited(full["rgb"], full["opacity"], background)
    groups = {f"K={level['samples']}": [level] for level in levels} | {"all": levels}
    out = {}
    for group, members in groups.items():
        rows = np.concatenate([m["rows"] for m in members])
        row = {"pixels": len(rows), "full": {"psnr_truth": metrics.psnr(reference[rows], truth[rows])}}
        colours = {v: variant_colours(members, v, background) for v in VARIANTS + (UNRECTIFIED,)}
        for v, c in colours.items():
            row[v] = agreement(c, reference[rows]) | {"psnr_truth": metrics.psnr(c, truth[rows])}
            if v not in (ORACLE, UNRECTIFIED):
                row[v]["vs_oracle"] = agreement(c, colours[ORACLE])
        out[group] = row
    return out


def measure_scene(name: str, size: tuple[int, int], renderer, bundle: OnnxBundle, policy, chunk: int) -> dict:
    folder, fmt, scale, target = SCENES[name]
    scene = datasets.load_scene(SHARED / folder, fmt, scale=scale)
    sources = datasets.nearest_sources(scene, target, source_pool(scene, scene.default_targets))
    views = datasets.get_views(scene, sources)
    target_view = scene.views[target]
    camera, truth = cropped_target(target_view.camera, target_view.image, *size)
    background = np.asarray(scene.background, np.float32)
    images = np.stack([v.image for v in views])
    encoded = bundle.encode_scene(images, [v.camera for v in views], scene.near, scene.far, background)
    tensors = SceneTensors(**{k: torch.from_numpy(v) for k, v in encoded.items()})
    near_far = torch.tensor([scene.near, scene.far], dtype=torch.float32)
    origins, directions = cams.target_rays(camera)
    start = time.perf_counter()
    full = render_full(renderer, tensors, near_far, origins, directions, chunk)
    full_seconds = time.perf_counter() - start
    # The read-back weights render what the bundle's renderer.onnx renders (a sample of rays).
    onnx_rgb, _, _ = bundle.render_rays(
        encoded, origins[::37], directions[::37], scene.near, scene.far, (scene.near, scene.far)
    )
    levels, view = fine_levels(renderer, tensors, near_far, policy, camera, background, full, chunk)
    # ... and the policy run here, with the guide variant, is the bundle's guided view.
    shipped = bundle.render_target(encoded, camera, scene.near, scene.far, background, sampling="guided")
    ours = composited(view.rgb, view.opacity, background)
    return {
        "target": target,
        "sources": sources,
        "size": f"{size[0]}x{size[1]}",
        "pixels": {
            "all": size[0] * size[1],
            "level0": len(origins) - sum(len(level["rows"]) for level in levels) - view.interpolated,
            "interpolated": view.interpolated,
            "at_k_samples": sum(len(level["rows"]) for level in levels),
        },
        "samples_per_pixel": view.network_samples / len(origins),
        "onnx_renderer_max_abs_difference": float(np.abs(onnx_rgb - full["rgb"][::37]).max()),
        "onnx_guided_view_max_abs_difference": float(np.abs(shipped.rgb.reshape(-1, 3) - ours).max()),
        "full_render_seconds": full_seconds,
        "scores": scores(levels, full, truth.reshape(-1, 3), background),
    }


def run(args) -> dict:
    torch.set_num_threads(1)
    bundle_dir = Path(args.bundle)
    renderer = load_renderer(bundle_dir)
    bundle = OnnxBundle(bundle_dir, threads=1)
    if bundle.policy is None:
        raise SystemExit(f"{bundle_dir}: no guided policy in the manifest")
    results = {
        "bundle": str(bundle_dir),
        "model_id": bundle.model_id,
        "policy": bundle.policy.to_json(),
        "machine": os.uname().nodename,
        "cpu": cpu_name(),
        "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "protocol": (
            "per target its 3 nearest source views (bench.sampling's rule), encoded by the bundle in ONNX Runtime; "
            "the renderer in PyTorch with the weights read back from renderer.onnx; the guided policy as shipped "
            "picks the pixels rendered at K samples, their samples, multiplicities and guide rays; each variant "
            "renders those pixels with them and is compared with the full render (all S samples, own heads), "
            "colours composited on the scene's background"
        ),
        "variants": {
            "guide": "heads of the nearest level-0 guide ray, from its S samples (as shipped)",
            "own-K": "own heads from the K samples alone (Q the ray's, K and V over the K samples)",
            "own-S": "own heads from all S samples (oracle)",
            "none": "no rectification",
            UNRECTIFIED: "not a variant: all S samples, no rectification (what the rectifiers change at all)",
        },
        "scenes": {},
    }
    for name, size in zip(args.scenes, args.sizes):
        with torch.no_grad():
            results["scenes"][name] = measure_scene(name, size, renderer, bundle, bundle.policy, args.chunk)
        print(name, json.dumps(results["scenes"][name]["scores"]["all"], default=float), flush=True)
    return results


def table(results: dict, title: str, variants: tuple[str, ...], cell: Callable[[dict], str]) -> str:
    """One measure of the variants, a row per scene and pixel group."""
    columns = ["scene", "size", "pixels", "samples", *variants]
    lines = [f"{title}\n", "| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    for name, scene in results["scenes"].items():
        for group, row in scene["scores"].items():
            cells = [f"{name} {scene['target']}", scene["size"], str(row["pixels"]), group]
            lines.append("| " + " | ".join(cells + [cell(row[v]) for v in variants]) + " |")
    return "\n".join(lines)


def tables(results: dict) -> str:
    def against(measure: dict) -> str:
        return f"{measure['psnr']:.2f} / {measure['max_abs']:.3f}"

    return "\n\n".join(
        [
            table(results, "Against the full render (PSNR dB / max abs)", VARIANTS + (UNRECTIFIED,), against),
            table(
                results,
                "Against own-S (PSNR dB / max abs)",
                ("guide", "own-K", "none"),
                lambda m: against(m["vs_oracle"]),
            ),
            table(
                results, "Against the ground truth (PSNR dB)", ("full",) + VARIANTS, lambda m: f"{m['psnr_truth']:.2f}"
            ),
        ]
    )


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--bundle", default="bundles/default")
    p.add_argument("--scenes", type=lambda s: s.split(","), default=list(SCENES))
    p.add_argument("--sizes", type=parse_sizes, default=parse_sizes("80x80,80x64"), help="one per scene")
    p.add_argument("--chunk", type=int, default=256, help="rays per PyTorch run")
    p.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    args = p.parse_args()
    if len(args.sizes) != len(args.scenes):
        raise SystemExit("--sizes: one size per scene")
    results = run(args)
    print(f"wrote {write_results(results, args.out, 'guided-heads')}\n")
    print(tables(results))


if __name__ == "__main__":
    main()
