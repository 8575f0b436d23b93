"""One rule for the renderer's passes over a view, shared by the PyTorch reference and ONNX Runtime:
an image_minmax bundle renders the same image through both, and its depth pass changes the colours."""

import numpy as np
import pytest
import torch

from scnerf_export.config import small_config
from scnerf_export.export.bundle import export_bundle
from scnerf_export.rigs import random_model, rig_cameras, smooth_pattern
from scnerf_export.runtime.onnx_pipeline import OnnxBundle
from scnerf_export.runtime.reference import render_view
from scnerf_export.runtime.view import image_depth_range, renderer_passes


def test_only_image_minmax_rectified_variants_take_a_depth_pass():
    assert renderer_passes(small_config("scnerf").replace(depth_norm="image_minmax")) == 2
    assert renderer_passes(small_config("scnerf")) == 1
    assert renderer_passes(small_config("mvsnerf").replace(depth_norm="image_minmax")) == 1


def test_image_depth_range_ignores_non_finite_depths_as_the_server_does():
    depth = np.array([3.0, np.nan, 2.5, np.inf, 4.0], np.float32)
    assert image_depth_range(depth, 1.0, 9.0) == (2.5, 4.0)
    assert image_depth_range(np.full(3, np.nan, np.float32), 1.0, 9.0) == (1.0, 9.0)


@pytest.mark.slow
def test_image_minmax_bundle_renders_the_same_through_pytorch_and_onnx_runtime(tmp_path):
    model = random_model(small_config("scnerf").replace(depth_norm="image_minmax"), seed=13)
    export_bundle(model, tmp_path, {"source_checkpoint": None})
    sources, target, near, far = rig_cameras(64, 96)
    images = np.stack([smooth_pattern(np.random.default_rng(i), 64, 96) for i in range(len(sources))])
    target = target.scaled(0.5)
    background = (0.2, 0.4, 0.6)
    want = render_view(model, images, sources, target, near, far, background)
    got = OnnxBundle(tmp_path).render_view(images, sources, target, near, far, background, chunk=333, band="network")
    assert want.opacity.std() > 0.01
    assert np.abs(got.rgb - want.rgb).max() <= 1e-3
    assert np.abs(got.depth - want.depth).max() <= 1e-3 * np.abs(want.depth).max()

    near_far = random_model(small_config("scnerf"), seed=13)
    with torch.no_grad():
        near_far.load_state_dict(model.state_dict())
    single_pass = render_view(near_far, images, sources, target, near, far, background)
    assert np.abs(single_pass.rgb - want.rgb).max() > 1e-3, "the depth pass must reach the colours"
