"""Guided sampling: the policy's pieces (the same cases as server/src/pipeline/guided.rs, so the
two implementations are held to one behaviour), the renderer's guided entry points against its full
forward, and a guided view through ONNX Runtime against the PyTorch reference."""

import numpy as np
import onnxruntime as ort
import pytest
import torch

from scnerf_export.config import small_config
from scnerf_export.export.bundle import GUIDED_GRAPHS, RendererGraph, example_inputs
from scnerf_export.export.guided import add_guided
from scnerf_export.export.manifest import GuidedPolicy, Manifest
from scnerf_export.export.reexport import renderer_state_from_current_graph
from scnerf_export.model.checkpoint import save_checkpoint
from scnerf_export.model.network import SCNeRF
from scnerf_export.model.renderer import composite_weights, nearest_heads, uniform_depths
from scnerf_export.rigs import random_model, rig_cameras, smooth_pattern, synthetic_rig
from scnerf_export.runtime.guided import (
    disagreeing,
    disagreement,
    first_level_pixels,
    level_pixels,
    nearest_guide,
    neighbours,
    render_guided,
    samples_at,
    select_samples,
    spread_samples,
    spread_weights,
    support,
)
from scnerf_export.runtime.onnx_pipeline import OnnxBundle
from scnerf_export.runtime.reference import encode_scene, render_target

from conftest import REPO

DEFAULT_BUNDLE = REPO / "bundles" / "default"


def test_levels_cover_every_pixel_once():
    width, height, step = 21, 13, 8
    seen = np.zeros((height, width), int)
    for v, u in first_level_pixels(width, height, step):
        seen[v, u] += 1
    spacing = step // 2
    while spacing >= 1:
        pixels = level_pixels(width, height, spacing)
        near, valid = neighbours(pixels, width, height, spacing)
        assert valid.any(axis=1).all()
        on_coarser = (near[..., 0] % (2 * spacing) == 0) & (near[..., 1] % (2 * spacing) == 0)
        assert on_coarser[valid].all()
        for v, u in pixels:
            seen[v, u] += 1
        spacing //= 2
    assert (seen == 1).all()


def test_neighbours_are_one_spacing_away():
    def near(v, u, size, spacing):
        found, valid = neighbours(np.array([[v, u]]), size, size, spacing)
        return [tuple(p) for p in found[0][valid[0]]]

    assert near(0, 4, 16, 4) == [(0, 0), (0, 8)]
    assert near(4, 4, 16, 4) == [(0, 0), (0, 8), (8, 0), (8, 8)]
    assert near(2, 15, 16, 1) == [(2, 14)]


def test_a_narrow_surface_is_sampled_exactly():
    score = np.zeros((1, 16), np.float32)
    score[0, 7], score[0, 8] = 0.6, 0.3
    index, multiplicity, owner = select_samples(score, 4, 1e-3)
    assert index.tolist() == [[6, 7, 8, 9]]
    assert multiplicity.tolist() == [[1.0] * 4]
    assert (owner >= 0).sum() == 4


def test_a_wide_surface_is_stood_for_by_its_samples():
    score = np.array([[0.0, 0.1, 0.1, 0.1, 0.1, 0.5, 0.1, 0.1, 0.1, 0.0, 0.0, 0.0]], np.float32)
    index, multiplicity, owner = select_samples(score, 3, 1e-3)
    assert index.tolist() == [[4, 5, 6]]
    assert multiplicity.tolist() == [[5.0, 1.0, 4.0]]
    spread = spread_weights(np.array([[0.5, 0.2, 0.4]], np.float32), multiplicity, owner)
    assert spread[0, 0] == pytest.approx(0.1) and spread[0, 5] == pytest.approx(0.2)
    assert spread[0, 9] == pytest.approx(0.1) and spread[0, 10] == 0.0


def test_ties_go_to_the_samples_nearest_the_best():
    index, _, _ = select_samples(np.zeros((1, 10), np.float32), 3, 1e-3)
    assert index.tolist() == [[0, 1, 2]]
    score = np.zeros((1, 10), np.float32)
    score[0, 5] = 1.0
    index, _, _ = select_samples(score, 5, 0.6)
    assert index.tolist() == [[3, 4, 5, 6, 7]]


def test_the_support_counts_the_dilated_samples_that_reach_the_threshold():
    score = np.array([[0.0, 0.0, 0.4, 0.0, 0.0, 0.0, 0.1, 0.1, 0.0, 0.0]], np.float32)
    assert support(score, 1e-3).tolist() == [7]
    assert support(score, 0.1).tolist() == [5]  # the dilated 0.05s (5 and 8) fall short
    assert support(np.zeros((1, 8), np.float32), 1e-3).tolist() == [0]


def test_a_pixel_rendered_again_keeps_its_support_and_spreads_the_rest():
    """The server's case (guided/tests.rs)."""
    score = np.zeros((1, 16), np.float32)
    score[0, 9] = 0.5
    index, multiplicity, owner = spread_samples(score, 8, 1e-3)
    assert index.tolist() == [[0, 2, 5, 7, 8, 9, 10, 13]]
    assert (owner >= 0).all()
    assert multiplicity.tolist() == [[2.0, 2.0, 3.0, 1.0, 1.0, 1.0, 2.0, 4.0]]
    wide = np.array([[0.2, 0.2, 0.2, 0.9, 0.2, 0.2, 0.2, 0.2]], np.float32)
    assert spread_samples(wide, 4, 1e-3)[0].tolist() == [[0, 2, 3, 5]]
    index, multiplicity, _ = spread_samples(score, 16, 1e-3)
    assert index.tolist() == [list(range(16))] and multiplicity.tolist() == [[1.0] * 16]


def test_a_thin_surface_runs_at_fewer_samples():
    """The server's case (guided/tests.rs): the support rounded up to a multiple of 4, at least
    ``min_samples``, at most the level's (or the edge's) count."""
    fitted = GuidedPolicy(step=4, samples=(4, 4), min_samples=8, edge_span=0.3, edge_samples=32)
    spans, supports = np.float32([0.0, 0.0, 0.0, 0.5, 0.5]), np.array([3, 9, 40, 3, 30])
    assert samples_at(fitted, 16, spans, supports).tolist() == [8, 12, 16, 8, 32]
    assert samples_at(fitted, 4, spans[:1], supports[:1]).tolist() == [4]
    plain = GuidedPolicy(step=4, samples=(4, 4), min_samples=None, edge_span=0.3, edge_samples=32)
    assert samples_at(plain, 16, spans, supports).tolist() == [16, 16, 16, 32, 32]
    with pytest.raises(ValueError):
        GuidedPolicy(min_samples=0)


def test_the_nearest_guide_ray_rounds_half_way_up():
    pixels = np.array([[4, 2], [3, 12], [0, 23]])
    assert nearest_guide(pixels, 3, 3, 8).tolist() == [3, 2, 2]


def test_pixels_that_disagree_with_their_neighbours_are_rendered_again_worst_first():
    """The server's case (guided.rs): a grey opaque 5 x 5 frame; at spacing 1, (1, 1) missed its
    neighbours' matter, (1, 3) is brighter than any, (3, 1) a little off, (3, 3) agrees."""
    outputs = np.tile(np.float32([0.5, 0.5, 0.5, 1.0]), (25, 1))
    outputs[1 * 5 + 1] = [0.15, 0.15, 0.15, 0.3]  # composited on a black background
    outputs[1 * 5 + 3, :3] = 0.9
    outputs[3 * 5 + 1, :3] = 0.55
    pixels = np.array([[1, 1], [1, 3], [3, 1], [3, 3]])
    near, valid = neighbours(pixels, 5, 5, 1)
    gap = disagreement(outputs[pixels[:, 0] * 5 + pixels[:, 1]], outputs[near[..., 0] * 5 + near[..., 1]], valid)
    np.testing.assert_allclose(gap, [0.7, 0.4, 0.05, 0.0], atol=1e-6)

    def verifying(tolerance, share):
        return GuidedPolicy(step=4, samples=(4, 4), verify_tolerance=tolerance, verify_share=share)

    assert disagreeing(verifying(0.1, 1.0), gap).tolist() == [True, True, False, False]
    assert disagreeing(verifying(0.01, 0.25), gap).tolist() == [True, False, False, False]
    assert disagreeing(verifying(0.01, 0.75), gap).tolist() == [True, True, True, False]
    plain = GuidedPolicy(step=4, samples=(4, 4), verify_tolerance=None, verify_share=None)
    assert not disagreeing(plain, gap).any()


def test_pixels_on_an_edge_run_at_more_samples():
    """The server's case (guided.rs): a grey opaque 5 x 5 frame but for a bright pixel (0, 2) on
    the grid of 2; at spacing 1 the five pixels beside it see their neighbours span 0.4 and run
    at the edge's 4 samples, the other 11 at the level's 2."""
    unverified = {"verify_tolerance": None, "verify_share": None}
    edges = GuidedPolicy(step=4, samples=(2, 2), smooth_max_step=0, edge_span=0.3, edge_samples=4, **unverified)
    np.testing.assert_array_equal(samples_at(edges, 2, np.float32([0.4, 0.3, 0.0]), np.array([8, 8, 8])), [4, 2, 2])
    assert samples_at(edges, 8, np.float32([1.0]), np.array([8])).tolist() == [8]
    plain = GuidedPolicy(step=4, samples=(2, 2), smooth_max_step=0, edge_span=None, edge_samples=None)
    assert samples_at(plain, 2, np.float32([1.0]), np.array([8])).tolist() == [2]
    with pytest.raises(ValueError):
        GuidedPolicy(edge_samples=None)

    width = height = 5
    grey = np.float32([0.5, 0.5, 0.5])

    def colour(origins):
        rgb = np.tile(grey, (len(origins), 1))
        rgb[(origins[:, 0] == 0) & (origins[:, 1] == 2)] = 0.9
        return rgb

    def outputs(origins, samples):
        n = len(origins)
        weights = np.full((n, samples), 1.0 / samples, np.float32)
        ones = np.ones(n, np.float32)
        return {"rgb": colour(origins), "depth": ones, "opacity": ones, "weights": weights}

    fine_runs = []

    def fine(origins, directions, index, multiplicity, guide_rows):
        fine_runs.append((index.shape[1], sorted(map(tuple, origins[:, :2].astype(int).tolist()))))
        return outputs(origins, index.shape[1])

    # Each ray's origin is its pixel (v, u, 0): the fakes see which pixel they render.
    v, u = np.meshgrid(np.arange(height), np.arange(width), indexing="ij")
    origins = np.stack([v.ravel(), u.ravel(), np.zeros(25)], axis=1).astype(np.float32)
    directions = np.tile(np.float32([0, 0, 1]), (25, 1))
    view = render_guided(
        edges, width, height, 8, origins, directions, np.zeros(3, np.float32), lambda o, d: outputs(o, 8), fine
    )
    coarser, *finest = fine_runs
    assert coarser == (2, [(0, 2), (2, 0), (2, 2), (2, 4), (4, 2)])
    beside = [(0, 1), (0, 3), (1, 1), (1, 2), (1, 3)]
    assert finest == [(2, [p for p in map(tuple, level_pixels(5, 5, 1).tolist()) if p not in beside]), (4, beside)]
    assert view.network_samples == 4 * 8 + 5 * 2 + 11 * 2 + 5 * 4
    assert view.samples_by_stage == {"level 0": 4 * 8, "grid 2": 5 * 2, "grid 1": 11 * 2 + 5 * 4}


def test_policy_fits_the_model():
    small = GuidedPolicy.for_model(small_config("scnerf"))
    assert small.samples == (32, 16, 16)
    # A pixel rendered again at no more than half the model's 32 samples.
    assert small.verify_samples == 16 and GuidedPolicy().verify_samples == 64
    with pytest.raises(ValueError):
        GuidedPolicy(step=6)
    with pytest.raises(ValueError):
        GuidedPolicy(samples=(8,))


@pytest.fixture(scope="module", params=["scnerf", "mvsnerf"])
def model_and_inputs(request):
    model = random_model(small_config(request.param), seed=3)
    rig = synthetic_rig(model.cfg, 64, 96, seed=5)
    with torch.no_grad():
        features = model.encode(rig["images"])
        volume = model.build_volume(features, rig["images"], rig["projections"], rig["depth_planes"])
    rays = slice(0, 6144, 97)
    args = (
        rig["ray_origins"][rays],
        rig["ray_directions"][rays],
        rig["near_far"],
        rig["near_far"],
        volume,
        rig["images"],
        features,
        rig["intrinsics"],
        rig["extrinsics"],
    )
    return model, args


def test_the_guide_renders_what_the_renderer_renders(model_and_inputs):
    model, args = model_and_inputs
    with torch.no_grad():
        full = model.renderer(*args)
        guide = model.renderer.guide(*args)
    for a, b in zip(full, (guide.rgb, guide.depth, guide.opacity)):
        assert torch.equal(a, b)
    assert torch.allclose(guide.weights.sum(dim=1), guide.opacity)
    assert set(guide.heads) == set(model.renderer.rectifiers())


def test_all_samples_with_their_own_heads_render_what_the_renderer_renders(model_and_inputs):
    """K = S samples, each standing for itself, with each ray's own heads: the full computation."""
    model, args = model_and_inputs
    origins, directions, near_far = args[:3]
    rays, s = origins.shape[0], model.cfg.samples
    index = torch.arange(s, dtype=torch.float32).expand(rays, s)
    with torch.no_grad():
        full = model.renderer(*args)
        guide = model.renderer.guide(*args)
        own = {name: nearest_heads(h, torch.arange(rays, dtype=torch.float32)) for name, h in guide.heads.items()}
        fine = model.renderer.render_samples(origins, directions, index, torch.ones(rays, s), *args[2:], own)
    for a, b in zip(full, (fine.rgb, fine.depth, fine.opacity)):
        assert (a - b).abs().max() <= 1e-5
    assert torch.allclose(uniform_depths(near_far, s)[5], near_far[0] + 5 * (near_far[1] - near_far[0]) / (s - 1))


def test_multiplicity_is_the_quadrature_of_the_samples_stood_for():
    """A sample standing for m samples of the same density composites like m of them."""
    sigma = torch.tensor([[0.3, 0.3, 0.3, 0.3, 2.0]])
    every = composite_weights(sigma)
    two = composite_weights(torch.tensor([[0.3, 0.3, 2.0]]) * torch.tensor([[1.0, 3.0, 1.0]]))
    assert torch.allclose(every[:, :4].sum(dim=1), two[:, :2].sum(dim=1))
    assert torch.allclose(every[:, 4], two[:, 2])


@pytest.fixture(scope="module")
def exported_scene(small_bundle):
    model, out, _ = small_bundle("scnerf")
    rng = np.random.default_rng(4)
    sources, target, near, far = rig_cameras(64, 96)
    images = np.stack([smooth_pattern(rng, 64, 96) for _ in sources])
    return model, out, images, sources, target, near, far


def test_guided_through_onnx_runtime_matches_pytorch(exported_scene):
    model, out, images, sources, target, near, far = exported_scene
    background = (0.2, 0.4, 0.6)
    with torch.no_grad():
        scene = encode_scene(model, images, sources, near, far, background)
    want = render_target(model, scene, target, near, far, background, sampling="guided")
    full = render_target(model, scene, target, near, far, background)
    bundle = OnnxBundle(out, threads=1)
    encoded = bundle.encode_scene(images, sources, near, far, background)
    got = bundle.render_target(encoded, target, near, far, background, sampling="guided", band="network")
    assert got.samples_per_ray == want.samples_per_ray < model.cfg.samples
    assert np.abs(got.rgb - want.rgb).max() <= 1e-3
    assert np.abs(got.opacity - want.opacity).max() <= 1e-3
    # Guided sampling approximates the full render (random weights: a loose bound).
    assert np.abs(want.rgb - full.rgb).mean() < 0.05


def test_add_guided_writes_graphs_that_agree_with_the_renderer(exported_scene, tmp_path):
    model, out, *_ = exported_scene
    checkpoint = tmp_path / "model.pt"
    save_checkpoint(checkpoint, model, {})
    stripped = tmp_path / "plain"
    stripped.mkdir()
    manifest = Manifest.load(out)
    for name, graph in manifest.graphs.items():
        if name not in GUIDED_GRAPHS:
            (stripped / graph.file).write_bytes((out / graph.file).read_bytes())
    manifest.graphs = {k: v for k, v in manifest.graphs.items() if k not in GUIDED_GRAPHS}
    manifest.guided = None
    manifest.save(stripped)
    again = add_guided(stripped, tmp_path / "guided", checkpoint)
    assert again.model_id == again.expected_model_id()
    assert again.provenance.guided_graphs["guide_max_abs_difference_from_renderer"] <= 1e-4
    assert set(GUIDED_GRAPHS) <= set(again.graphs)
    assert Manifest.load(tmp_path / "guided").guided == again.guided == GuidedPolicy.for_model(manifest.config)


def test_the_default_bundles_renderer_weights_read_back_render_what_it_renders():
    """add-guided without a checkpoint reads the renderer's weights back from its graph; on the
    default bundle they must render what its renderer.onnx renders: within the render parity bound
    (1e-3; depth relative to its range). The encoder and volume net are random (seeded: the inputs,
    and so the rounding, must not depend on the tests that ran before); wrong weights miss by far
    more."""
    torch.manual_seed(0)
    model = SCNeRF(Manifest.load(DEFAULT_BUNDLE).config).eval()
    model.renderer.load_state_dict(renderer_state_from_current_graph(DEFAULT_BUNDLE / "renderer.onnx", model))
    feeds = example_inputs(model, blocks=(3, 2), rays=256)["renderer"]
    session = ort.InferenceSession(str(DEFAULT_BUNDLE / "renderer.onnx"), providers=["CPUExecutionProvider"])
    got = session.run(None, {k: v.numpy() for k, v in feeds.items()})
    with torch.no_grad():
        want = RendererGraph(model)(*feeds.values())
    (rgb, depth, opacity), (want_rgb, want_depth, want_opacity) = got[:3], (w.numpy() for w in want[:3])
    assert np.abs(rgb - want_rgb).max() <= 1e-3 and np.abs(opacity - want_opacity).max() <= 1e-3
    assert np.abs(depth - want_depth).max() <= 1e-4 * np.abs(want_depth).max()
