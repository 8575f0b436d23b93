"""PyTorch vs ONNX Runtime: every sub-graph within 1e-4, full renders within 1e-3, for mvsnerf and
scnerf at two image sizes; and the committed Rust fixtures still match the exported bundle."""

import json

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch
from PIL import Image

from scnerf_export.cameras import camera_from_json
from scnerf_export.export.bundle import EncoderGraph, RendererGraph, VolumeGraph, renderer_input_names
from scnerf_export.rigs import synthetic_rig
from scnerf_export.runtime.onnx_pipeline import OnnxBundle
from scnerf_export.runtime.reference import render_view

SIZES = [(64, 96), (128, 64)]


@pytest.fixture(scope="module", params=["mvsnerf", "scnerf"])
def exported(request, small_bundle):
    return small_bundle(request.param)


def subgraph_inputs(model, height, width):
    rig = synthetic_rig(model.cfg, height, width, seed=height + width)
    with torch.no_grad():
        features = model.encode(rig["images"])
        volume = model.build_volume(features, rig["images"], rig["projections"], rig["depth_planes"])
    rays = {**rig, "depth_range": rig["near_far"] * torch.tensor([1.1, 0.9]), "volume": volume, "features": features}
    rays["ray_origins"], rays["ray_directions"] = rig["ray_origins"][::13], rig["ray_directions"][::13]
    return {
        "encoder": {"images": rig["images"]},
        "volume": {k: rays[k] for k in ("features", "images", "projections", "depth_planes")},
        "renderer": {k: rays[k] for k in renderer_input_names(model)},
    }


@pytest.mark.parametrize("height,width", SIZES)
def test_each_subgraph_matches_pytorch(exported, height, width):
    model, out, _ = exported
    inputs = subgraph_inputs(model, height, width)
    modules = {"encoder": EncoderGraph(model), "volume": VolumeGraph(model), "renderer": RendererGraph(model)}
    for name, module in modules.items():
        session = ort.InferenceSession(str(out / f"{name}.onnx"), providers=["CPUExecutionProvider"])
        got = session.run(None, {k: v.numpy() for k, v in inputs[name].items()})
        with torch.no_grad():
            want = module(*inputs[name].values())
        want = want if isinstance(want, tuple) else (want,)
        for g, w in zip(got, want):
            assert g.shape == tuple(w.shape)
            assert np.abs(g - w.numpy()).max() <= 1e-4, f"{name} at {height}x{width}"


@pytest.mark.parametrize("height,width", SIZES)
def test_full_render_matches_pytorch(exported, height, width):
    model, out, _ = exported
    rng = np.random.default_rng(0)
    from scnerf_export.rigs import rig_cameras, smooth_pattern

    sources, target, near, far = rig_cameras(height, width)
    images = np.stack([smooth_pattern(rng, height, width) for _ in sources])
    target = target.scaled(0.5)
    want = render_view(model, images, sources, target, near, far, background=(0.2, 0.4, 0.6))
    got = OnnxBundle(out).render_view(
        images, sources, target, near, far, background=(0.2, 0.4, 0.6), chunk=333, band="network"
    )
    assert want.opacity.std() > 0.01
    assert np.abs(got.rgb - want.rgb).max() <= 1e-3
    assert np.abs(got.depth - want.depth).max() <= 1e-3 * np.abs(want.depth).max()


def test_manifest_describes_the_graphs(exported):
    model, out, manifest = exported
    assert manifest.variant == model.cfg.variant
    assert manifest.config == model.cfg
    for name, graph in manifest.graphs.items():
        proto = onnx.load(out / graph.file)
        declared = {
            i.name: [d.dim_param or d.dim_value for d in i.type.tensor_type.shape.dim]
            for i in list(proto.graph.input) + list(proto.graph.output)
        }
        for io in graph.inputs + graph.outputs:
            assert declared[io.name] == io.shape, f"{name}.{io.name}"
        assert graph.input_names() == [i.name for i in proto.graph.input]


def pixels_beyond(errors: np.ndarray, tolerance: float) -> int:
    """Pixels of an (H, W[, C]) error image with some value beyond ``tolerance``."""
    return int((errors.reshape(errors.shape[0], errors.shape[1], -1).max(axis=2) > tolerance).sum())


def test_committed_fixtures_match_the_committed_bundle(parity_fixtures):
    """The Python twin of the Rust parity test: decode each case as the server does, run the
    committed bundle in ONNX Runtime, compare with the committed PyTorch outputs."""
    bundle = OnnxBundle(parity_fixtures / "bundle")
    cases = sorted((parity_fixtures / "cases").iterdir())
    assert cases, "no committed fixture cases"
    for case in cases:
        request = json.loads((case / "request.json").read_text())
        expected = json.loads((case / "expected.json").read_text())
        images = np.stack(
            [
                np.asarray(Image.open(case / f"source_{i}.png").convert("RGB"), np.float32) / 255
                for i in range(len(request["sources"]))
            ]
        )
        cameras = [camera_from_json(s["camera"]) for s in request["sources"]]
        target = camera_from_json(request["target"])
        near, far, background = request["near"], request["far"], tuple(request["background"])
        scene = bundle.encode_scene(images, cameras, near, far, background)
        tolerances = expected["tolerances"]
        for sampling, suffix in (("full", ""), ("guided", "_guided")):
            got = bundle.render_target(
                scene, target, near, far, background, chunk=1000, sampling=sampling, band="network"
            )
            want = {
                n: np.fromfile(case / expected["files"][n + suffix], dtype="<f4").reshape(
                    expected["shapes"][n + suffix]
                )
                for n in ("rgb", "depth", "opacity")
            }
            # Guided sampling spares the pixels whose samples the runtimes may rank apart on a
            # near-tie (the Rust test's guided_spared): one in a thousand, rounded up.
            spared = -(-want["depth"].size // 1000) if sampling == "guided" else 0
            rel_depth = np.abs(got.depth - want["depth"]) / np.maximum(np.abs(want["depth"]), 1e-3)
            assert pixels_beyond(np.abs(got.rgb - want["rgb"]), tolerances["rgb_max_abs"]) <= spared, sampling
            assert pixels_beyond(rel_depth, tolerances["depth_max_rel"]) <= spared, sampling
            assert pixels_beyond(np.abs(got.opacity - want["opacity"]), tolerances["opacity_max_abs"]) <= spared, (
                sampling
            )
        # The same pixels took the same paths of guided sampling as in PyTorch.
        assert got.samples_per_ray == expected["guided_samples_per_ray"]
        assert got.paths == expected["guided_paths"]


def test_committed_fixtures_exercise_every_path_of_guided_sampling(parity_fixtures):
    """Some pixel of the cases takes the neighbours' mean, runs at an edge's samples and is
    rendered again: the Rust parity test holds each path to PyTorch's."""
    paths = [
        json.loads((case / "expected.json").read_text())["guided_paths"]
        for case in sorted((parity_fixtures / "cases").iterdir())
    ]
    for path in ("interpolated", "on_edge", "rendered_again"):
        assert any(p[path] > 0 for p in paths), path


def test_the_renderer_runs_its_attention_cores_in_ray_groups(exported):
    """scnerf renderers carry one Loop per rectifier (scnerf_export.export.ray_groups) and match PyTorch
    for a single ray, a whole group and a group plus one (the Loop, the rest, both)."""
    from scnerf_export.export.ray_groups import RAYS_PER_GROUP

    model, out, _ = exported
    proto = onnx.load(out / "renderer.onnx")
    rectifiers = (model.renderer.geometry is not None) + (model.renderer.appearance is not None)
    assert [n.op_type for n in proto.graph.node].count("Loop") == rectifiers
    height, width = SIZES[0]
    inputs = subgraph_inputs(model, height, width)["renderer"]
    rig = synthetic_rig(model.cfg, height, width, seed=height + width)  # the rays subgraph_inputs thins out
    session = ort.InferenceSession(str(out / "renderer.onnx"), providers=["CPUExecutionProvider"])
    for rays in (1, RAYS_PER_GROUP, RAYS_PER_GROUP + 1):
        feeds = {**inputs, "ray_origins": rig["ray_origins"][:rays], "ray_directions": rig["ray_directions"][:rays]}
        got = session.run(None, {k: v.numpy() for k, v in feeds.items()})
        with torch.no_grad():
            want = RendererGraph(model)(*feeds.values())
        for g, w in zip(got, want):
            assert g.shape == tuple(w.shape)
            assert np.abs(g - w.numpy()).max() <= 1e-4, f"{rays} rays"
