"""`init-scnerf`: an scnerf network initialised from mvsnerf weights renders what the mvsnerf
network renders (<= 1e-5), through PyTorch and ONNX Runtime, on synthetic rigs and on a real
scene with the public checkpoint; and it is a real scnerf network (training can move it)."""

import numpy as np
import pytest
import torch

from scnerf_export.cameras import target_rays
from scnerf_export.config import small_config
from scnerf_export.data import datasets
from scnerf_export.evaluate.eval import downscale_target
from scnerf_export.export.bundle import export_bundle
from scnerf_export.model.checkpoint import init_scnerf, load_checkpoint, load_mvsnerf, scnerf_from_mvsnerf
from scnerf_export.rigs import random_model, rig_cameras, synthetic_rig
from scnerf_export.runtime.onnx_pipeline import OnnxBundle
from scnerf_export.runtime.reference import encode_scene, render_rays

from conftest import shared_dir

TOLERANCE = 1e-5


def render_rig(model, height=64, width=96, grad=False):
    rig = synthetic_rig(model.cfg, height, width, seed=3)
    with torch.set_grad_enabled(grad):
        features = model.encode(rig["images"])
        volume = model.build_volume(features, rig["images"], rig["projections"], rig["depth_planes"])
        return model.renderer(
            rig["ray_origins"],
            rig["ray_directions"],
            rig["near_far"],
            rig["near_far"],
            volume,
            rig["images"],
            features,
            rig["intrinsics"],
            rig["extrinsics"],
        )


def assert_same_renders(a, b):
    for name, x, y in zip(("rgb", "depth", "opacity"), a, b):
        x, y = np.asarray(x), np.asarray(y)
        assert np.abs(x - y).max() <= TOLERANCE, f"{name} differs by {np.abs(x - y).max():.3g}"


@pytest.fixture(scope="module")
def small_pair():
    mvsnerf = random_model(small_config("mvsnerf"), seed=5)
    torch.manual_seed(1)
    return mvsnerf, scnerf_from_mvsnerf(mvsnerf)


def test_initialised_scnerf_renders_what_mvsnerf_renders(small_pair):
    mvsnerf, scnerf = small_pair
    assert scnerf.cfg.variant == "scnerf"
    mvs, sc = render_rig(mvsnerf), render_rig(scnerf)
    assert float(mvs[2].min()) < 0.9 < float(mvs[2].max()), "a degenerate rig would prove nothing"
    assert_same_renders(mvs, sc)


def test_rectifiers_start_silent_but_receive_gradients(small_pair):
    scnerf = scnerf_from_mvsnerf(small_pair[0])
    rgb, _, _ = render_rig(scnerf, height=32, width=64, grad=True)
    rgb.sum().backward()
    for rectifier in (scnerf.renderer.geometry, scnerf.renderer.appearance):
        assert not rectifier.w_o.weight.detach().any()
        assert float(rectifier.w_o.weight.grad.abs().max()) > 0.0, "W_o must receive a gradient"


@pytest.mark.slow
def test_onnx_bundles_of_both_render_the_same(small_pair, tmp_path):
    renders = []
    for model in small_pair:
        export_bundle(model, tmp_path / model.cfg.variant, {"source_checkpoint": None})
        bundle = OnnxBundle(tmp_path / model.cfg.variant, threads=1)
        sources, target, near, far = rig_cameras(64, 96)
        rig = synthetic_rig(model.cfg, 64, 96, seed=3)
        images = rig["images"].numpy().transpose(0, 2, 3, 1)
        r = bundle.render_view(images, sources, target, near, far, band="network")
        renders.append((r.rgb, r.depth, r.opacity))
    assert_same_renders(*renders)


def test_init_checkpoint_names_the_public_weights_and_licence(public_checkpoint, tmp_path):
    path = init_scnerf(public_checkpoint, tmp_path / "init.pt")
    model, provenance = load_checkpoint(path)
    base = provenance["derived_from"]
    assert model.cfg.variant == "scnerf"
    assert base["source_sha256"] == "84c2a397760d5e717c21faee9c4f8f8f8a1ba22b378b10971c44f4a0b932c124"
    assert base["licence"] == "MIT" and "Permission is hereby granted" in base["licence_text"]
    assert provenance["training"]["steps"] == 0


@pytest.fixture(scope="module")
def scan37():
    scene_dir = shared_dir() / "data" / "dtu_scan37"
    if not scene_dir.is_dir():
        pytest.skip(f"DTU scan37 not found at {scene_dir} (../shared is absent on this machine)")
    scene = datasets.load_scene(scene_dir, "dtu")
    return scene, datasets.get_views(scene, ["33", "31", "25"]), downscale_target(scene.views["32"], 0.125)


@pytest.mark.slow
def test_public_weights_render_the_same_through_pytorch(public_checkpoint, scan37):
    scene, sources, target = scan37
    mvsnerf, _ = load_mvsnerf(public_checkpoint)
    scnerf = scnerf_from_mvsnerf(mvsnerf)
    origins, directions = target_rays(target.camera)
    with torch.no_grad():
        encoded = encode_scene(
            mvsnerf, np.stack([v.image for v in sources]), [v.camera for v in sources], scene.near, scene.far
        )
        renders = [
            render_rays(m, encoded, origins[::7], directions[::7], scene.near, scene.far, (scene.near, scene.far), 512)
            for m in (mvsnerf, scnerf)
        ]
    assert_same_renders(*renders)


@pytest.mark.slow
def test_public_weights_render_the_same_through_onnx_runtime(public_checkpoint, scan37, tmp_path):
    scene, sources, target = scan37
    mvsnerf, provenance = load_mvsnerf(public_checkpoint)
    renders = []
    for model in (mvsnerf, scnerf_from_mvsnerf(mvsnerf)):
        export_bundle(model, tmp_path / model.cfg.variant, provenance)
        assert (tmp_path / model.cfg.variant / "LICENSE.mvsnerf").is_file()
        r = OnnxBundle(tmp_path / model.cfg.variant).render_view(
            np.stack([v.image for v in sources]),
            [v.camera for v in sources],
            target.camera,
            scene.near,
            scene.far,
            band="network",
        )
        renders.append((r.rgb, r.depth, r.opacity))
    assert_same_renders(*renders)
