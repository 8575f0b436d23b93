"""The variants of bench.guided_heads on a tiny random model: at all S samples, each standing for
itself, a ray's own heads (from S, or computed over its samples) render what the full renderer
renders, the heads of another ray or none do not; at fewer samples, the guide variant is what the
renderer's guided entry point renders."""

import pytest
import torch

from bench.guided_heads import render_variants
from scnerf_export.config import small_config
from scnerf_export.model.renderer import nearest_heads
from scnerf_export.rigs import random_model, synthetic_rig
from scnerf_export.runtime.reference import SceneTensors


@pytest.fixture(scope="module")
def rays():
    model = random_model(small_config("scnerf"), seed=3)
    rig = synthetic_rig(model.cfg, 32, 32, seed=5)
    with torch.no_grad():
        features = model.encode(rig["images"])
        volume = model.build_volume(features, rig["images"], rig["projections"], rig["depth_planes"])
        scene = SceneTensors(rig["images"], features, volume, rig["intrinsics"], rig["extrinsics"])
        picked = slice(0, 1024, 41)
        origins, directions, near_far = rig["ray_origins"][picked], rig["ray_directions"][picked], rig["near_far"]
        tensors = (volume, rig["images"], features, rig["intrinsics"], rig["extrinsics"])
        full = model.renderer.guide(origins, directions, near_far, near_far, *tensors)
    return model.renderer, scene, tensors, near_far, origins, directions, full


def test_own_heads_over_all_samples_render_the_full_render(rays):
    renderer, scene, _, near_far, origins, directions, full = rays
    count, samples = origins.shape[0], renderer.cfg.samples
    index = torch.arange(samples, dtype=torch.float32).expand(count, samples)
    another_rays = {name: h.roll(1, dims=0) for name, h in full.heads.items()}
    with torch.no_grad():
        shaded = render_variants(
            renderer, scene, near_far, origins, directions, index, torch.ones(count, samples), another_rays, full.heads
        )
    assert (shaded["own-S"].rgb - full.rgb).abs().max() <= 1e-5
    assert (shaded["own-K"].rgb - full.rgb).abs().max() <= 1e-5
    # The 1e-5 above tells heads apart: another ray's, or none, land further off.
    assert (shaded["guide"].rgb - full.rgb).abs().max() > 1e-4
    assert (shaded["none"].rgb - full.rgb).abs().max() > 1e-4


def test_the_guide_variant_is_the_renderers_guided_rendering(rays):
    renderer, scene, tensors, near_far, origins, directions, full = rays
    count, samples = origins.shape[0], renderer.cfg.samples
    index = torch.arange(1, samples, 4, dtype=torch.float32).expand(count, -1)
    multiplicity = torch.full(index.shape, 4.0)
    guide_rows = torch.zeros(count)
    heads = {name: nearest_heads(h, guide_rows) for name, h in full.heads.items()}
    with torch.no_grad():
        shaded = render_variants(renderer, scene, near_far, origins, directions, index, multiplicity, heads, heads)
        want = renderer.render_samples(origins, directions, index, multiplicity, near_far, near_far, *tensors, heads)
    assert (shaded["guide"].rgb - want.rgb).abs().max() <= 1e-6
    assert (shaded["guide"].weights - want.weights).abs().max() <= 1e-6
