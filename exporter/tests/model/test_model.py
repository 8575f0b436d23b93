"""Properties of the PyTorch network that the server relies on."""

import unittest.mock

import numpy as np
import pytest
import torch

from scnerf_export import cameras as cams
from scnerf_export.config import ModelConfig, small_config
from scnerf_export.model.cost_volume import transposed_conv_as_subpixel
from scnerf_export.model.layers import BatchStatNorm, affine_inverse
from scnerf_export.model.renderer import composite_weights
from scnerf_export.rigs import random_model, rig_cameras, smooth_pattern
from scnerf_export.runtime.reference import render_view


def scene(height=64, width=96, seed=0):
    rng = np.random.default_rng(seed)
    sources, target, near, far = rig_cameras(height, width)
    return np.stack([smooth_pattern(rng, height, width) for _ in sources]), sources, target, near, far


@pytest.mark.parametrize("variant", ["mvsnerf", "scnerf", "scnerf-geometry", "scnerf-appearance"])
def test_render_does_not_depend_on_chunk_size(variant):
    model = random_model(small_config(variant), seed=1)
    images, sources, target, near, far = scene()
    target = target.scaled(0.25)
    a = render_view(model, images, sources, target, near, far, chunk=7)
    b = render_view(model, images, sources, target, near, far, chunk=target.width * target.height)
    assert a.opacity.std() > 0.01, "degenerate render: the test would not see chunk effects"
    np.testing.assert_allclose(a.rgb, b.rgb, atol=1e-6)
    np.testing.assert_allclose(a.depth, b.depth, rtol=1e-6)
    np.testing.assert_allclose(a.opacity, b.opacity, atol=1e-6)


def test_render_is_deterministic():
    model = random_model(small_config("scnerf"), seed=2)
    images, sources, target, near, far = scene()
    a = render_view(model, images, sources, target.scaled(0.5), near, far)
    b = render_view(model, images, sources, target.scaled(0.5), near, far)
    assert np.array_equal(a.rgb, b.rgb) and np.array_equal(a.depth, b.depth)


def test_background_fills_what_is_not_opaque():
    model = random_model(small_config("mvsnerf"), seed=3)
    images, sources, target, near, far = scene()
    black = render_view(model, images, sources, target.scaled(0.5), near, far, background=(0, 0, 0))
    white = render_view(model, images, sources, target.scaled(0.5), near, far, background=(1, 1, 1))
    np.testing.assert_allclose(white.rgb - black.rgb, np.repeat(1 - black.opacity[..., None], 3, -1), atol=1e-6)


def test_affine_inverse_matches_numpy():
    rng = np.random.default_rng(0)
    m = np.eye(4)
    m[:3, :4] = rng.normal(size=(3, 4))
    np.testing.assert_allclose(affine_inverse(torch.from_numpy(m)).numpy(), np.linalg.inv(m), atol=1e-10)


def test_compositing_matches_the_cumulative_product():
    sigma = torch.rand(5, 17, dtype=torch.float64) * 2
    alpha = 1 - torch.exp(-sigma)
    transmit = torch.cumprod(torch.cat([torch.ones(5, 1, dtype=torch.float64), 1 - alpha + 1e-10], -1), -1)[:, :-1]
    torch.testing.assert_close(composite_weights(sigma), alpha * transmit)


def test_depth_is_the_weighted_sample_depth_of_an_opaque_wall():
    """A ray through a single very dense sample renders that sample's depth with opacity 1."""
    sigma = torch.zeros(1, 32)
    sigma[0, 20] = 50.0
    w = composite_weights(sigma)
    z = torch.linspace(2.0, 4.0, 32)
    assert float(w.sum()) == pytest.approx(1.0, abs=1e-6)
    assert float((w * z).sum()) == pytest.approx(float(z[20]), abs=1e-5)


def test_target_rays_go_through_pixel_centres():
    K = cams.pinhole(100.0, 32, 24)
    cam = cams.Camera(K, cams.look_at((0.3, -0.2, -2.0), (0, 0, 0), up=(0, -1, 0)), 32, 24)
    origins, directions = cams.target_rays(cam)
    points = origins.astype(np.float64) + directions.astype(np.float64) * 2.5
    uvz = (cam.w2c[:3, :3] @ points.T).T + cam.w2c[:3, 3]
    pix = (K @ uvz.T).T
    uv = pix[:, :2] / pix[:, 2:]
    v, u = np.mgrid[0:24, 0:32]
    np.testing.assert_allclose(uv, np.stack([u.ravel(), v.ravel()], -1), atol=1e-4)
    np.testing.assert_allclose(uvz[:, 2], 2.5, atol=1e-5)


def test_pose_conventions_reach_one_canonical_camera():
    K = cams.pinhole(50.0, 16, 16)
    cam = cams.Camera(K, cams.look_at((1.0, 0.5, -3.0), (0, 0, 0), up=(0, -1, 0)), 16, 16)
    gl_c2w = cam.c2w @ cams.OPENGL_TO_OPENCV
    for matrix, kind, axes in [
        (cam.w2c, "world_to_camera", "opencv"),
        (cam.c2w, "camera_to_world", "opencv"),
        (gl_c2w, "camera_to_world", "opengl"),
        (np.linalg.inv(gl_c2w), "world_to_camera", "opengl"),
    ]:
        np.testing.assert_allclose(cams.Camera.from_pose(K, matrix, 16, 16, kind, axes).w2c, cam.w2c, atol=1e-12)


def test_config_round_trips_and_rejects_bad_values():
    cfg = small_config("scnerf-geometry")
    assert ModelConfig.from_dict(cfg.to_dict()) == cfg
    with pytest.raises(ValueError):
        ModelConfig(variant="nerf")
    with pytest.raises(ValueError):
        ModelConfig(depth_planes=100)
    with pytest.raises(ValueError):
        ModelConfig.from_dict({**cfg.to_dict(), "colour": 1})
    with pytest.raises(ValueError, match="skip_layer"):  # no layer after it would read E(x) again
        ModelConfig(trunk_layers=6, skip_layer=5)


def test_positional_encoding_uses_the_reference_channel_order():
    """[x, sin(2^k x) for k, cos(2^k x) for k], coordinates fastest: the public checkpoint's trunk
    reads its 63 inputs in this order (MVSNeRF's Embedder.embed), not NeRF's interleaved one."""
    from scnerf_export.model.layers import frequency_encoding

    x = torch.tensor([[0.1, 0.2, 0.3]])
    got = frequency_encoding(x, 2)[0]
    a = x[0]
    want = torch.cat([a, torch.sin(a), torch.sin(2 * a), torch.cos(a), torch.cos(2 * a)])
    torch.testing.assert_close(got, want)


def test_rectifier_equals_textbook_multihead_attention():
    """The rectifier's folded form (rank-2 queries, W_k folded into the two score terms) computes
    paper Eq. (ss) as written: tokens are the C channels, each embedded by its S values."""
    from scnerf_export.model.rectifiers import SampleAxisAttention

    cfg = small_config()
    torch.manual_seed(0)
    attention = SampleAxisAttention(cfg, key_channels=7).double()
    for p in attention.parameters():  # the default init leaves the scores too flat to tell apart
        torch.nn.init.normal_(p, std=0.5)
    rays, s, c, heads, dk = 3, cfg.samples, cfg.width, cfg.heads, cfg.head_dim
    query = torch.randn(rays, cfg.depth_embedding_channels + cfg.direction_embedding_channels, dtype=torch.float64)
    keys = torch.randn(rays, s, 7, dtype=torch.float64)
    values = torch.randn(rays, s, c, dtype=torch.float64)

    q_tokens = attention.query_m3(query)[:, :, None].expand(-1, -1, s)  # (R,C,S): q_c along S
    k_tokens = attention.key_embedding(keys).transpose(1, 2)
    v_tokens = values.transpose(1, 2)

    def split_heads(x):
        return x.view(rays, c, heads, dk).transpose(1, 2)  # (R,h,C,dk)

    q = split_heads(attention.w_q(q_tokens))
    k = split_heads(attention.w_k(k_tokens))
    v = split_heads(attention.w_v(v_tokens))
    weights = torch.softmax(q @ k.transpose(-1, -2) / dk**0.5, dim=-1)
    concatenated = (weights @ v).transpose(1, 2).reshape(rays, c, heads * dk)
    want = torch.relu(v_tokens + attention.w_o(concatenated)).transpose(1, 2)

    got = attention(query, keys.permute(2, 0, 1), values)  # keys channels first, as sampled
    torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)
    assert weights.max() > 0.5, "scores too flat: the check would pass for a wrong key path"


def test_trunk_skip_layer_reads_the_concatenation():
    """M1's layer after the skip reads [E(x), h]; it is computed as two products, so check it
    against the concatenation written out (float64)."""
    from scnerf_export.model.trunk import TrunkM1

    cfg = small_config()
    torch.manual_seed(0)
    trunk = TrunkM1(cfg).double()
    embedding = torch.randn(11, cfg.position_embedding_channels, dtype=torch.float64)
    features = torch.randn(11, cfg.point_feature_channels, dtype=torch.float64)

    gate = trunk.feature_gate(features)
    h = embedding
    for i, layer in enumerate(trunk.linears):
        h = torch.relu(layer(h) * gate)
        if i == cfg.skip_layer:
            h = torch.cat([embedding, h], dim=-1)
    torch.testing.assert_close(trunk(embedding, features), h, rtol=1e-12, atol=1e-12)


def test_colours_are_the_border_padded_samples():
    """The colour taps go through grid_sample's align_corners=False path on a clamped grid; they
    must read what border padding with align_corners=True reads, at and beyond the image edges."""
    from scnerf_export.model.points import sample_views, view_grid

    images, sources, *_ = scene(height=12, width=16)
    images = torch.from_numpy(images).permute(0, 3, 1, 2).double()
    intrinsics = torch.from_numpy(cams.stack_intrinsics(sources)).double()
    extrinsics = torch.from_numpy(cams.stack_extrinsics(sources)).double()
    torch.manual_seed(0)
    points = torch.randn(500, 3, dtype=torch.float64) * 2.0
    colours, _ = sample_views(points, images, None, intrinsics, extrinsics)

    rgb = colours.view(len(sources), 4, -1)[:, :3]
    for i in range(len(sources)):
        grid = view_grid(points, intrinsics[i], extrinsics[i], 12, 16).view(1, 1, -1, 2)
        assert (grid.abs() > 1).any() and (grid.abs() < 1).all(dim=-1).any(), "need points in and out"
        want = torch.nn.functional.grid_sample(
            images[i : i + 1], grid, mode="bilinear", padding_mode="border", align_corners=True
        ).view(3, -1)
        torch.testing.assert_close(rgb[i], want, rtol=1e-12, atol=1e-12)


def test_a_transposed_convolution_is_its_sub_pixel_convolution():
    """The form the volume graphs export G2's up blocks in: the same sums, interleaved."""
    conv = torch.nn.ConvTranspose3d(5, 3, 3, stride=2, padding=1, output_padding=1, bias=False).double()
    x = torch.randn(1, 5, 3, 4, 6, dtype=torch.float64)
    with torch.no_grad():
        assert torch.allclose(transposed_conv_as_subpixel(x, conv.weight), conv(x), atol=1e-12)


def test_the_exported_norm_is_the_batch_norm():
    """BatchStatNorm as exported (one BatchNormalization with E[x²] - E[x]²) against PyTorch's."""
    norm = BatchStatNorm(4, 0.01, 1e-5, "batch").double()
    with torch.no_grad():
        norm.weight.uniform_(0.5, 1.5), norm.bias.uniform_(-0.5, 0.5)
    x = torch.randn(2, 4, 3, 5, 6, dtype=torch.float64) * 3 + 2
    eager = norm(x)
    with unittest.mock.patch("torch.compiler.is_exporting", return_value=True), torch.no_grad():
        exported = norm(x)
    assert torch.allclose(exported, eager, atol=1e-10)
