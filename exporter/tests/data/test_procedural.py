"""Tests of the procedural multi-view data generator (scnerf_export.data.procedural)."""

from __future__ import annotations

import numpy as np
import pytest

from scnerf_export.data.procedural import (
    GAPS,
    LAYOUTS,
    VAL_SEED0,
    Camera,
    Light,
    Material,
    Plane,
    ProceduralDataset,
    Sphere,
    World,
    build_dataset,
    intrinsics,
    load_scene,
    look_at,
    make_scene,
    pick_sources,
    render_view,
    save_preview,
    save_scene,
    split_seed,
)
from scnerf_export.data.procedural.layouts import OBJECT_TARGET

W, H = 80, 64  # small but not square, so a swapped axis shows up


@pytest.fixture(scope="module")
def scenes() -> dict[str, object]:
    return {layout: make_scene(3, layout, n_views=12, width=W, height=H) for layout in LAYOUTS}


# ----------------------------------------------------------------------------------------------
# determinism


def test_same_seed_gives_identical_arrays():
    a = make_scene(11, "outdoor", n_views=2, width=48, height=32)
    b = make_scene(11, "outdoor", n_views=2, width=48, height=32)
    assert (a.near, a.far) == (b.near, b.far)
    for va, vb in zip(a.views, b.views):
        assert np.array_equal(va.image, vb.image)
        assert np.array_equal(va.depth, vb.depth)
        assert np.array_equal(va.alpha, vb.alpha)
        assert np.array_equal(va.camera.w2c, vb.camera.w2c)


def test_different_seed_or_layout_gives_different_scene():
    a = make_scene(11, "object", n_views=2, width=48, height=32)
    b = make_scene(12, "object", n_views=2, width=48, height=32)
    c = make_scene(11, "forward", n_views=2, width=48, height=32)
    assert not np.array_equal(a.views[0].image, b.views[0].image)
    assert not np.array_equal(a.views[0].depth, b.views[0].depth)
    assert not np.array_equal(a.views[0].image, c.views[0].image)


def test_scene_does_not_depend_on_resolution():
    """Same seed at another size: same cameras, same near/far, same picture (up to sampling)."""
    lo = make_scene(5, "forward", n_views=3, width=40, height=32, supersample=1)
    hi = make_scene(5, "forward", n_views=3, width=80, height=64, supersample=1)
    assert (lo.near, lo.far) == (hi.near, hi.far)
    for a, b in zip(lo.views, hi.views):
        assert np.array_equal(a.camera.w2c, b.camera.w2c)
        assert np.isclose(b.camera.K[0, 0], 2 * a.camera.K[0, 0])
    # the 2x2 mean of the fine image lands half a fine pixel off the coarse centres; compare loosely
    fine = hi.views[0].image.reshape(32, 2, 40, 2, 3).mean(axis=(1, 3))
    assert np.mean(np.abs(fine - lo.views[0].image)) < 0.06


def test_full_size_render():
    scene = make_scene(2, "object", n_views=1, width=640, height=512, supersample=1)
    view = scene.views[0]
    assert view.image.shape == (512, 640, 3) and view.depth.shape == (512, 640)
    finite = view.depth[np.isfinite(view.depth)]
    assert finite.min() >= scene.near and finite.max() <= scene.far


# ----------------------------------------------------------------------------------------------
# geometry and camera conventions


def _plain(color=(0.6, 0.5, 0.4)) -> Material:
    return Material(pattern="flat", colors=np.array([color] * 3))


def test_sphere_depth_matches_analytic_z_depth():
    center, radius = np.array([0.3, 2.0, 0.5]), 0.8
    world = World(
        [Sphere(center=center, material=_plain(), radius=radius)],
        Light(direction=np.array([0.0, -1.0, 1.0]) / np.sqrt(2)),
    )
    K = intrinsics(64, 48, 50.0)
    w2c = look_at(np.array([1.0, -2.5, 1.7]), center + np.array([0.2, 0.1, -0.1]))
    cam = Camera(K=K, w2c=w2c, width=64, height=48)
    view = render_view(world, cam, supersample=1)

    # analytic, entirely in the camera frame: ray t*d with d = [(u-cx)/fx, (v-cy)/fy, 1] has z-depth t
    c = w2c[:3, :3] @ center + w2c[:3, 3]
    v, u = np.mgrid[0:48, 0:64].astype(np.float64)
    d = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)
    dd, dc = (d * d).sum(-1), d @ c
    disc = dc**2 - dd * (c @ c - radius**2)
    hit = disc >= 0
    z = (dc - np.sqrt(np.where(hit, disc, 0.0))) / dd
    assert hit.sum() > 300 and (~hit).sum() > 300  # the silhouette is inside the image
    assert np.array_equal(np.isfinite(view.depth), hit)
    assert np.max(np.abs(view.depth[hit] - z[hit])) < 1e-4
    assert np.all(np.isinf(view.depth[~hit])) and np.all(view.alpha[~hit] == 0) and np.all(view.alpha[hit] == 1)
    assert np.all(view.image[~hit] == 0)


def test_rotations_are_proper_and_intrinsics_valid(scenes):
    for scene in scenes.values():
        for view in scene.views:
            cam = view.camera
            R = cam.w2c[:3, :3]
            assert cam.K.dtype == np.float64 and cam.w2c.dtype == np.float64
            assert np.allclose(R @ R.T, np.eye(3), atol=1e-12)
            assert np.isclose(np.linalg.det(R), 1.0)
            assert np.array_equal(cam.w2c[3], [0, 0, 0, 1])
            assert cam.K[0, 0] > 0 and cam.K[1, 1] > 0 and np.array_equal(cam.K[2], [0, 0, 1])
            assert (cam.width, cam.height) == (W, H)
            # pixel centres at integer coordinates: the optical axis hits ((W-1)/2, (H-1)/2)
            uv, _ = cam.project(cam.center[None] + cam.forward[None])
            assert np.allclose(uv[0], [(W - 1) / 2, (H - 1) / 2])


def test_object_layout_looks_at_the_object(scenes):
    """OpenCV axes: the object centre projects near the image centre, in front of the camera,
    and 'up' in the world is 'up' (smaller v) in the image."""
    for view in scenes["object"].views:
        uv, z = view.camera.project(np.stack([OBJECT_TARGET, OBJECT_TARGET + [0, 0, 0.3]]))
        assert z[0] > 0
        assert abs(uv[0, 0] - (W - 1) / 2) < 0.1 * W and abs(uv[0, 1] - (H - 1) / 2) < 0.1 * H
        assert uv[1, 1] < uv[0, 1]


def _bilinear(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    x0, y0 = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
    fx, fy = uv[:, 0] - x0, uv[:, 1] - y0
    if img.ndim == 3:
        fx, fy = fx[:, None], fy[:, None]
    top = img[y0, x0] * (1 - fx) + img[y0, x0 + 1] * fx
    bot = img[y0 + 1, x0] * (1 - fx) + img[y0 + 1, x0 + 1] * fx
    return top * (1 - fy) + bot * fy


def _reproject(a, b, step=3):
    """Pixels of view a (every ``step``-th), their world points, and where they land in view b."""
    v, u = np.mgrid[1 : a.camera.height - 1 : step, 1 : a.camera.width - 1 : step]
    uv_a = np.stack([u.ravel(), v.ravel()], axis=-1).astype(np.float64)
    depth_a = a.depth[v.ravel(), u.ravel()].astype(np.float64)
    ok = np.isfinite(depth_a)
    uv_a, depth_a = uv_a[ok], depth_a[ok]
    uv_b, z_b = b.camera.project(a.camera.unproject(uv_a, depth_a))
    # one pixel of margin, so the bilinear lookups below (and a half-pixel shift) stay inside b
    inside = (
        (z_b > 0)
        & (uv_b[:, 0] >= 0)
        & (uv_b[:, 1] >= 0)
        & (uv_b[:, 0] < b.camera.width - 2)
        & (uv_b[:, 1] < b.camera.height - 2)
    )
    return uv_a[inside], uv_b[inside], z_b[inside]


def test_multiview_consistency_on_a_textured_plane():
    """A diffuse, solid-textured plane: reprojecting a pixel of A with its depth into B finds the
    same depth and colour in B (bilinear).  Half a pixel of convention error would fail it."""
    mat = Material(
        pattern="noise", colors=np.array([[0.1, 0.2, 0.7], [0.9, 0.8, 0.2], [0.2, 0.8, 0.3]]), scale=0.3, seed=5
    )
    world = World([Plane(center=np.zeros(3), material=mat)], Light(direction=np.array([0.3, -0.2, 0.93])))
    K = intrinsics(96, 80, 55.0)
    a = render_view(
        world, Camera(K, look_at(np.array([-0.8, -3.0, 2.2]), np.array([0.2, 0.5, 0.0])), 96, 80), quantize=False
    )
    b = render_view(
        world, Camera(K, look_at(np.array([1.2, -2.6, 2.8]), np.array([0.0, 0.8, 0.0])), 96, 80), quantize=False
    )
    uv_a, uv_b, z_b = _reproject(a, b, step=2)
    assert len(uv_a) > 500
    ia = uv_a.astype(int)
    rel = np.abs(_bilinear(b.depth, uv_b) - z_b) / z_b
    col = np.abs(_bilinear(b.image, uv_b) - a.image[ia[:, 1], ia[:, 0]])
    assert rel.max() < 2e-3
    assert col.mean() < 0.004 and np.percentile(col, 99) < 0.02
    # the test is sharp enough to see a half-pixel convention error (e.g. cx = W/2)
    shifted = np.abs(_bilinear(b.image, uv_b + 0.5) - a.image[ia[:, 1], ia[:, 0]])
    assert shifted.mean() > 3 * col.mean()
    assert (np.abs(_bilinear(b.depth, uv_b + 0.5) - z_b) / z_b).max() > 10 * rel.max()


def test_multiview_depth_consistency_in_generated_scenes(scenes):
    """In every layout, depth reprojected from one view agrees with the other view's depth wherever
    the point is not occluded (most pixels)."""
    for layout, scene in scenes.items():
        a = scene.views[0]
        b = scene.views[pick_sources(scene, 0, "small")[0]]
        uv_a, uv_b, z_b = _reproject(a, b, step=2)
        x0, y0 = np.floor(uv_b[:, 0]).astype(int), np.floor(uv_b[:, 1]).astype(int)
        corners = np.stack([b.depth[y0 + dy, x0 + dx] for dy in (0, 1) for dx in (0, 1)], axis=-1)
        # consistent: b's depth around the landing point brackets the reprojected depth
        agree = (corners.min(-1) <= z_b * 1.01) & (corners.max(-1) >= z_b * 0.99)
        assert len(z_b) > 200, layout
        assert agree.mean() > 0.9, (layout, agree.mean())
        # b never sees *through* a reprojected surface (only occluders in front of it)
        assert np.mean(corners.min(-1) > z_b * 1.01) < 0.02, layout


# ----------------------------------------------------------------------------------------------
# layouts, images and sources


def test_images_are_finite_and_in_range(scenes):
    for scene in scenes.values():
        for view in scene.views:
            assert view.image.shape == (H, W, 3) and view.image.dtype == np.float32
            assert view.depth.shape == (H, W) and view.depth.dtype == np.float32
            assert view.alpha.shape == (H, W) and view.alpha.dtype == np.float32
            assert np.all(np.isfinite(view.image)) and view.image.min() >= 0 and view.image.max() <= 1
            assert np.all(np.isfinite(view.alpha)) and view.alpha.min() >= 0 and view.alpha.max() <= 1
            assert not np.any(np.isnan(view.depth))
            assert view.image.std() > 0.03  # textured, not empty
            assert np.array_equal(np.round(view.image * 255) / 255, view.image)  # 8-bit quantised


def test_layout_depth_ranges(scenes):
    for layout, scene in scenes.items():
        depths = np.concatenate([v.depth[np.isfinite(v.depth)] for v in scene.views])
        assert scene.near > 0 and depths.min() >= scene.near and depths.max() <= scene.far, layout
        if layout == "object":
            assert 1.8 < scene.far / scene.near < 2.6  # DTU: 4.525 / 2.125 = 2.13
            assert 1.5 < scene.near < 2.5
            assert all(v.alpha.min() == 0 and v.alpha.max() == 1 for v in scene.views)
            assert all(np.mean(v.alpha > 0) > 0.15 for v in scene.views)  # the object fills the view
        elif layout == "forward":
            assert 3 < scene.far / scene.near < 20
            assert all(v.alpha.min() == 1 for v in scene.views)
        else:
            assert scene.far / scene.near > 50 and scene.far > 100 and scene.near < 5
            assert all(v.alpha.min() == 1 for v in scene.views)  # the sky is opaque
            assert all(np.mean(v.depth > 0.8 * scene.far) > 0.02 for v in scene.views)  # sky visible


def test_gap_settings_move_sources_away(scenes):
    for layout, scene in scenes.items():
        centers = np.stack([v.camera.center for v in scene.views])
        means = []
        for gap in GAPS:
            dists = []
            for t in range(len(scene.views)):
                src = pick_sources(scene, t, gap)
                assert len(src) == 3 and t not in src and len(set(src)) == 3
                dists.append(np.linalg.norm(centers[src] - centers[t], axis=-1).mean())
            means.append(np.mean(dists))
        assert means[0] < means[1] < means[2], (layout, means)
        # small = the three nearest, nearest first (the reference)
        d0 = np.linalg.norm(centers - centers[0], axis=-1)
        d0[0] = np.inf
        assert pick_sources(scene, 0, "small") == list(np.argsort(d0, kind="stable")[:3])


def test_pick_sources_rejects_bad_arguments(scenes):
    with pytest.raises(ValueError):
        pick_sources(scenes["object"], 0, "huge")
    tiny = make_scene(1, "object", n_views=3, width=32, height=32)
    with pytest.raises(ValueError):
        pick_sources(tiny, 0, "small")


# ----------------------------------------------------------------------------------------------
# cache, dataset, preview


def test_cache_round_trip_is_exact(tmp_path, scenes):
    scene = scenes["outdoor"]
    save_scene(scene, tmp_path / "s.npz")
    back = load_scene(tmp_path / "s.npz")
    assert (back.near, back.far, back.layout, back.seed) == (scene.near, scene.far, scene.layout, scene.seed)
    for a, b in zip(scene.views, back.views):
        for name in ("image", "depth", "alpha"):
            assert np.array_equal(getattr(a, name), getattr(b, name)), name
            assert getattr(a, name).dtype == getattr(b, name).dtype
        assert np.array_equal(a.camera.K, b.camera.K) and np.array_equal(a.camera.w2c, b.camera.w2c)


def test_dataset_stream_and_cache(tmp_path):
    paths = build_dataset(tmp_path, n_scenes=3, n_views=10, width=32, height=32, supersample=1)
    assert [p.exists() for p in paths] == [True] * 3
    assert [load_scene(p).layout for p in paths] == list(LAYOUTS)
    ds = ProceduralDataset(
        "train", n_scenes=3, n_views=10, width=32, height=32, gaps=GAPS, cache_dir=tmp_path, supersample=1, seed=4
    )
    stream = iter(ds)
    examples = [next(stream) for _ in range(6)]
    again = iter(
        ProceduralDataset(
            "train", n_scenes=3, n_views=10, width=32, height=32, gaps=GAPS, cache_dir=tmp_path, supersample=1, seed=4
        )
    )
    for ex in examples:
        assert len(ex.sources) == 3 and ex.target_index not in ex.source_indices
        assert ex.near < ex.far and ex.layout in LAYOUTS and ex.gap in GAPS
        assert ex.source_indices == pick_sources(ds.scene(ex.scene_index), ex.target_index, ex.gap)
        assert np.array_equal(ex.target.image, next(again).target.image)  # the stream is seeded
    fixed = list(
        ProceduralDataset("val", n_scenes=1, n_views=10, width=32, height=32, gaps=GAPS, supersample=1).fixed_examples(
            targets_per_scene=2
        )
    )
    assert len(fixed) == 6 and all(ex.scene_seed == VAL_SEED0 for ex in fixed)


def test_train_and_validation_seeds_never_overlap():
    assert split_seed("train", 0) == 0 and split_seed("val", 0) == VAL_SEED0
    assert split_seed("train", VAL_SEED0 - 1) < split_seed("val", 0)
    with pytest.raises(ValueError):
        split_seed("train", VAL_SEED0)
    with pytest.raises(ValueError):
        ProceduralDataset("train", n_scenes=VAL_SEED0 + 1)


def test_preview_png(tmp_path, scenes):
    from PIL import Image

    save_preview(scenes["forward"], tmp_path / "p.png")
    with Image.open(tmp_path / "p.png") as img:
        assert img.size[0] > 4 * W and img.size[1] > 2 * H
