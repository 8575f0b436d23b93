"""Scene loaders: synthetic round trips in every format, error handling, and the real scenes of
../shared/data (skipped when that folder is absent)."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from scnerf_export.cameras import Camera, look_at, opencv_w2c_to_opengl_c2w, opengl_c2w_to_opencv_w2c
from scnerf_export.data import datasets as D
from scnerf_export.data.dataparsers.dtu import DTU_SCALE
from scnerf_export.data.datasets import load_scene
from scnerf_export.data.depth_range import from_poses
from scnerf_export.data.scene import View, crop_view, resize_view

from conftest import REPO


def shared_data_dir() -> Path | None:
    """../shared/data next to the repository root, or $SCNERF_SHARED(/data)."""
    cands = []
    env = os.environ.get("SCNERF_SHARED")
    if env:
        cands += [Path(env) / "data", Path(env)]
    cands.append(REPO.parent / "shared" / "data")
    for c in cands:
        if (c / "dtu_scan37").is_dir() or (c / "nerf_synthetic_lego").is_dir():
            return c
    return None


# ----------------------------------------------------------------------------- synthetic scenes

W, H = 64, 48
F = 70.0


def rot(rng) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def make_cameras(n=4, seed=0, K=None, width=W, height=H, radius=4.0):
    rng = np.random.default_rng(seed)
    if K is None:
        K = np.array([[F, 0, width / 2], [0, F, height / 2], [0, 0, 1.0]])
    cams = []
    for i in range(n):
        ang = 2 * math.pi * i / n + rng.uniform(-0.2, 0.2)
        c = np.array([radius * math.cos(ang), radius * math.sin(ang), rng.uniform(0.5, 1.5)])
        w2c = look_at(c, target=rng.normal(scale=0.1, size=3))
        cams.append(Camera(K.copy(), w2c, width, height))
    return cams


def rand_images(n, width=W, height=H, seed=1, channels=3):
    rng = np.random.default_rng(seed)
    return [rng.integers(0, 256, size=(height, width, channels), dtype=np.uint8) for _ in range(n)]


def w2c_to_gl_c2w(w2c):
    return np.linalg.inv(w2c) @ np.diag([1.0, -1.0, -1.0, 1.0])


def rot_to_quat(R):
    """(qw, qx, qy, qz) of a rotation matrix (Shepperd's method)."""
    t = np.trace(R)
    if t > 0:
        s = math.sqrt(t + 1.0) * 2
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = math.sqrt(1.0 + R[i, i] - R[j, j] - R[k, k]) * 2
        q = [0.0] * 4
        q[0] = (R[k, j] - R[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (R[j, i] + R[i, j]) / s
        q[1 + k] = (R[k, i] + R[i, k]) / s
    return q


def write_blender(root: Path, cams, images, split="train", angle=None, name_fmt="r_{i}"):
    (root / split).mkdir(parents=True, exist_ok=True)
    if angle is None:
        angle = 2 * math.atan(0.5 * cams[0].width / cams[0].K[0, 0])
    frames = []
    for i, (c, im) in enumerate(zip(cams, images)):
        name = name_fmt.format(i=i)
        Image.fromarray(im).save(root / split / f"{name}.png")
        frames.append(
            {"file_path": f"./{split}/{name}", "rotation": 0.1, "transform_matrix": w2c_to_gl_c2w(c.w2c).tolist()}
        )
    (root / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": angle, "frames": frames}))


def write_nerfstudio(root: Path, cams, images, per_frame=False, extra=None):
    (root / "images").mkdir(parents=True, exist_ok=True)
    frames = []
    top = {}
    for i, (c, im) in enumerate(zip(cams, images)):
        Image.fromarray(im).save(root / "images" / f"frame_{i:05d}.png")
        intr = {
            "fl_x": c.K[0, 0],
            "fl_y": c.K[1, 1],
            "cx": c.K[0, 2] + 0.5,
            "cy": c.K[1, 2] + 0.5,
            "w": c.width,
            "h": c.height,
        }
        fr = {"file_path": f"images/frame_{i:05d}.png", "transform_matrix": w2c_to_gl_c2w(c.w2c).tolist()}
        if per_frame:
            fr.update(intr)
        else:
            top = intr
        frames.append(fr)
    data = {"camera_model": "OPENCV", **top, "frames": frames}
    data.update(extra or {})
    (root / "transforms.json").write_text(json.dumps(data))


def write_llff(root: Path, cams, images, bounds):
    (root / "images").mkdir(parents=True, exist_ok=True)
    rows = []
    for i, (c, im) in enumerate(zip(cams, images)):
        Image.fromarray(im).save(root / "images" / f"IMG_{i:04d}.png")
        c2w = np.linalg.inv(c.w2c)
        R, t = c2w[:3, :3], c2w[:3, 3]
        llff = np.stack([R[:, 1], R[:, 0], -R[:, 2]], axis=1)  # [down, right, back]
        m = np.concatenate([llff, t[:, None], np.array([[c.height], [c.width], [c.K[0, 0]]])], axis=1)
        rows.append(np.concatenate([m.ravel(), bounds[i]]))
    np.save(root / "poses_bounds.npy", np.array(rows))


def write_colmap(root: Path, cams, images, model="PINHOLE", points=None, sub="sparse/0"):
    (root / "images").mkdir(parents=True, exist_ok=True)
    mdir = root / sub
    mdir.mkdir(parents=True, exist_ok=True)
    cam_lines, img_lines = ["# Camera list", "# CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]"], ["# Image list"]
    for i, (c, im) in enumerate(zip(cams, images)):
        Image.fromarray(im).save(root / "images" / f"{i:03d}.png")
        fx, fy, cx, cy = c.K[0, 0], c.K[1, 1], c.K[0, 2] + 0.5, c.K[1, 2] + 0.5
        if model == "PINHOLE":
            params = [fx, fy, cx, cy]
        elif model == "SIMPLE_RADIAL":
            params = [fx, cx, cy, 0.01]
        elif model == "OPENCV":
            params = [fx, fy, cx, cy, 0.01, 0, 0, 0]
        else:
            params = [fx, cx, cy]
        cam_lines.append(f"{i + 1} {model} {c.width} {c.height} " + " ".join(repr(float(p)) for p in params))
        q = rot_to_quat(c.w2c[:3, :3])
        t = c.w2c[:3, 3]
        img_lines.append(f"{i + 1} " + " ".join(repr(float(x)) for x in (*q, *t)) + f" {i + 1} {i:03d}.png")
        img_lines.append("" if i % 2 == 0 else "10.5 12.5 -1 20.0 30.0 -1")  # POINTS2D may be empty
    (mdir / "cameras.txt").write_text("\n".join(cam_lines) + "\n")
    (mdir / "images.txt").write_text("\n".join(img_lines) + "\n")
    if points is not None:
        lines = ["# 3D point list"]
        for j, p in enumerate(points):
            track = " ".join(f"{k + 1} 0" for k in range(len(cams)))
            lines.append(f"{j + 1} {float(p[0])!r} {float(p[1])!r} {float(p[2])!r} 128 128 128 0.5 {track}")
        (mdir / "points3D.txt").write_text("\n".join(lines) + "\n")


def write_dtu(root: Path, cams, images, depth_line="425.0 2.5"):
    """cams in the scaled world (1/200 of mm), 640x512."""
    cdir = root / "Cameras" / "train"
    idir = root / "Rectified" / "scan1_train"
    cdir.mkdir(parents=True)
    idir.mkdir(parents=True)
    ids = []
    for i, (c, im) in enumerate(zip(cams, images)):
        vid = 3 * i + 2
        ids.append(str(vid))
        w2c = c.w2c.copy()
        w2c[:3, 3] /= DTU_SCALE
        K = c.K.copy()
        K[:2] /= 4.0
        txt = "extrinsic\n" + "\n".join(" ".join(f"{x:.17g}" for x in r) for r in w2c)
        txt += "\n\nintrinsic\n" + "\n".join(" ".join(f"{x:.17g}" for x in r) for r in K)
        txt += f"\n\n{depth_line}\n"
        (cdir / f"{vid:08d}_cam.txt").write_text(txt)
        Image.fromarray(im).save(idir / f"rect_{vid + 1:03d}_3_r5000.png")
    return ids


def assert_cam_equal(a: Camera, b: Camera, tol=1e-9):
    assert (a.width, a.height) == (b.width, b.height)
    np.testing.assert_allclose(a.K, b.K, atol=tol, rtol=0)
    np.testing.assert_allclose(a.w2c, b.w2c, atol=tol, rtol=0)


POINTS = np.array([[0.0, 0.0, 0.0], [0.3, -0.2, 0.1], [-0.25, 0.15, 0.3], [0.1, 0.4, -0.2]])


# ----------------------------------------------------------------------------- round trips


def test_opengl_opencv_conversions_are_inverse():
    rng = np.random.default_rng(3)
    w2c = np.eye(4)
    w2c[:3, :3] = rot(rng)
    w2c[:3, 3] = rng.normal(size=3)
    gl = opencv_w2c_to_opengl_c2w(w2c)
    np.testing.assert_allclose(opengl_c2w_to_opencv_w2c(gl), w2c, atol=1e-12)
    # OpenGL camera looks down -z: a point in front of an OpenCV camera has negative z in GL
    p_cam_gl = np.linalg.inv(gl) @ np.array([*np.linalg.inv(w2c)[:3, :3] @ [0, 0, 2.0] + np.linalg.inv(w2c)[:3, 3], 1])
    assert p_cam_gl[2] == pytest.approx(-2.0)


def test_blender_round_trip_and_alpha(tmp_path):
    cams = make_cameras(3)
    ims = rand_images(3, channels=4)
    ims[0][..., 3] = 0
    ims[1][..., 3] = 255
    write_blender(tmp_path, cams, ims)
    for bg, expect in ((None, 1.0), ((0.0, 0.0, 0.0), 0.0)):
        scene = load_scene(tmp_path, "blender", background=bg)
        assert scene.near == 2.0 and scene.far == 6.0
        assert sorted(scene.views) == ["r_0", "r_1", "r_2"]
        for i, c in enumerate(cams):
            assert_cam_equal(scene.views[f"r_{i}"].camera, c)
        assert np.all(scene.views["r_0"].image == expect)
        np.testing.assert_allclose(scene.views["r_1"].image, ims[1][..., :3] / 255.0, atol=1e-6)
        a = ims[2][..., 3:] / 255.0
        np.testing.assert_allclose(scene.views["r_2"].image, ims[2][..., :3] / 255.0 * a + expect * (1 - a), atol=1e-6)
        assert scene.views["r_2"].image.dtype == np.float32 and scene.views["r_2"].image.shape == (H, W, 3)


def test_blender_skips_missing_images_and_names_collisions(tmp_path):
    cams = make_cameras(4)
    ims = rand_images(4)
    write_blender(tmp_path, cams[:2], ims[:2], split="train")
    write_blender(tmp_path, cams[2:], ims[2:], split="val")
    (tmp_path / "val" / "r_1.png").unlink()  # listed but absent: skipped
    scene = load_scene(tmp_path, "blender")
    # train r_0, r_1 and val r_0 collide on "r_0": every name gets its split
    assert sorted(scene.views) == ["train/r_0", "train/r_1", "val/r_0"]
    assert_cam_equal(scene.views["val/r_0"].camera, cams[2])
    assert scene.default_sources is None and scene.default_targets is None


def test_nerfstudio_round_trip(tmp_path):
    K = np.array([[80.0, 0, 30.25], [0, 75.0, 25.5], [0, 0, 1]])
    cams = make_cameras(3, K=K)
    ims = rand_images(3)
    write_nerfstudio(tmp_path, cams, ims, per_frame=True, extra={"near": 1.5, "far": 7.0})
    scene = load_scene(tmp_path, "nerfstudio")
    assert (scene.near, scene.far) == (1.5, 7.0)
    for i, c in enumerate(cams):
        v = scene.views[f"frame_{i:05d}"]
        assert_cam_equal(v.camera, c)
        np.testing.assert_allclose(v.image, ims[i] / 255.0, atol=1e-6)


def test_nerfstudio_without_near_far_takes_the_poses_and_the_arguments_win(tmp_path):
    cams = make_cameras(4)
    write_nerfstudio(tmp_path, cams, rand_images(4))
    scene = load_scene(tmp_path, "nerfstudio")
    assert (scene.near, scene.far) == pytest.approx(from_poses(cams))
    scene = load_scene(tmp_path, "nerfstudio", near=1.0, far=5.0)
    assert (scene.near, scene.far) == (1.0, 5.0)
    assert_cam_equal(scene.views["frame_00001"].camera, cams[1])


def test_nerfstudio_with_parallel_cameras_needs_near_far(tmp_path):
    K = np.array([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1.0]])
    cams = [Camera(K, look_at((x, 0.0, 0.0), target=(x, 5.0, 0.0)), W, H) for x in (0.0, 1.0, 2.0)]
    write_nerfstudio(tmp_path, cams, rand_images(3))
    with pytest.raises(ValueError, match="near/far"):
        load_scene(tmp_path, "nerfstudio")


def test_nerfstudio_intrinsics_follow_the_image_size(tmp_path):
    """w/h in the file describe a 2x larger image than the one on disk: K is rescaled."""
    cams = make_cameras(2)
    big = [Camera(c.resized(2 * W, 2 * H).K, c.w2c, 2 * W, 2 * H) for c in cams]
    write_nerfstudio(tmp_path, big, rand_images(2), extra={"near": 1, "far": 5})
    scene = load_scene(tmp_path, "nerfstudio")
    assert_cam_equal(scene.views["frame_00000"].camera, cams[0], tol=1e-9)


def test_llff_round_trip(tmp_path):
    cams = make_cameras(4)
    ims = rand_images(4)
    bounds = np.array([[1.2, 8.0], [1.0, 9.0], [1.5, 7.0], [1.1, 8.5]])
    write_llff(tmp_path, cams, ims, bounds)
    scene = load_scene(tmp_path, "llff")
    assert scene.near == 1.0 and scene.far == 9.0
    assert list(scene.views) == [f"IMG_{i:04d}" for i in range(4)]
    for i, c in enumerate(cams):
        v = scene.views[f"IMG_{i:04d}"]
        assert_cam_equal(v.camera, c)
        np.testing.assert_allclose(v.image, ims[i] / 255.0, atol=1e-6)


def test_llff_scale_uses_downsampled_folder_or_resizes(tmp_path):
    cams = make_cameras(2)
    ims = rand_images(2)
    write_llff(tmp_path, cams, ims, np.array([[1.0, 5.0], [1.0, 5.0]]))
    resized = load_scene(tmp_path, "llff", scale=0.5)
    sub = tmp_path / "images_2"
    sub.mkdir()
    for i in range(len(ims)):
        Image.fromarray(np.zeros((H // 2, W // 2, 3), np.uint8)).save(sub / f"IMG_{i:04d}.png")
    folder = load_scene(tmp_path, "llff", scale=0.5)
    for scene in (resized, folder):
        v = scene.views["IMG_0001"]
        assert (v.camera.width, v.camera.height) == (W // 2, H // 2)
        # LLFF's convention: the principal point is the image centre at every resolution
        np.testing.assert_allclose(v.camera.K, [[F / 2, 0, W / 4], [0, F / 2, H / 4], [0, 0, 1]], atol=1e-12)
    assert np.all(folder.views["IMG_0000"].image == 0)  # came from images_2
    assert resized.views["IMG_0000"].image.std() > 0


@pytest.mark.parametrize("model", ["PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "OPENCV"])
def test_colmap_round_trip(tmp_path, model):
    K = np.array([[F, 0, 31.0], [0, F if model.startswith("SIMPLE") else 72.0, 22.75], [0, 0, 1]])
    cams = make_cameras(3, K=K)
    ims = rand_images(3)
    write_colmap(tmp_path, cams, ims, model=model, points=POINTS)
    if model in ("SIMPLE_RADIAL", "OPENCV"):  # data/test_lens.py: what they load as undistorted
        with pytest.warns(UserWarning, match="distortion ignored"):
            scene = load_scene(tmp_path, "colmap", ignore_distortion=True)
    else:
        scene = load_scene(tmp_path, "colmap")
    assert list(scene.views) == ["000", "001", "002"]
    for i, c in enumerate(cams):
        assert_cam_equal(scene.views[f"{i:03d}"].camera, c)
        np.testing.assert_allclose(scene.views[f"{i:03d}"].image, ims[i] / 255.0, atol=1e-6)
    # near/far from the points' depths: all points lie within ~0.5 of the origin at ~4 units
    zs = np.concatenate([c.project(POINTS)[1] for c in cams])
    assert scene.near == pytest.approx(0.9 * np.percentile(zs, 1))
    assert scene.far == pytest.approx(1.1 * np.percentile(zs, 99))
    assert 0 < scene.near < zs.min() and scene.far > zs.max()


def test_colmap_without_points_takes_the_poses_and_the_arguments_win(tmp_path):
    cams = make_cameras(4)
    write_colmap(tmp_path, cams, rand_images(4), sub=".")
    scene = load_scene(tmp_path, "colmap")
    assert (scene.near, scene.far) == pytest.approx(from_poses(cams))
    scene = load_scene(tmp_path, "colmap", near=0.5, far=9)
    assert (scene.near, scene.far) == (0.5, 9.0)


def test_dtu_round_trip(tmp_path):
    K = np.array([[1446.17, 0, 331.6], [0, 1441.59, 265.54], [0, 0, 1]])
    cams = make_cameras(3, K=K, width=640, height=512, radius=3.3)
    ims = rand_images(3, width=640, height=512)
    ids = write_dtu(tmp_path / "scan1", cams, ims)
    scene = load_scene(tmp_path / "scan1", "dtu")
    assert scene.near == pytest.approx(2.125, abs=1e-12)
    assert scene.far == pytest.approx(4.525, abs=1e-12)
    assert sorted(scene.views, key=int) == ids
    for vid, c, im in zip(ids, cams, ims):
        v = scene.views[vid]
        assert_cam_equal(v.camera, c, tol=1e-9)
        np.testing.assert_allclose(v.image, im / 255.0, atol=1e-6)
        assert v.mask is None and v.depth is None


def test_dtu_mask_and_depth_transform(tmp_path):
    cams = make_cameras(1, K=np.array([[1400.0, 0, 320], [0, 1400, 256], [0, 0, 1]]), width=640, height=512)
    [vid] = write_dtu(tmp_path / "scan1", cams, rand_images(1, width=640, height=512))
    mask = np.zeros((1200, 1600), np.uint8)
    mask[400:800, 600:1000] = 255  # -> 800x600: [200:400, 300:500] -> crop: [156:356, 220:420]
    (tmp_path / "scan1" / "mask_1600x1200").mkdir()
    Image.fromarray(mask).save(tmp_path / "scan1" / "mask_1600x1200" / f"{int(vid):03d}.png")
    depth = np.zeros((1200, 1600), np.float32)
    depth[400:800, 600:1000] = 600.0  # mm
    ddir = tmp_path / "scan1" / "Depths_raw" / "scan1"
    ddir.mkdir(parents=True)
    with open(ddir / f"depth_map_{int(vid):04d}.pfm", "wb") as f:
        f.write(b"Pf\n1600 1200\n-1\n")
        f.write(np.flipud(depth).astype("<f4").tobytes())
    v = load_scene(tmp_path / "scan1", "dtu").views[vid]
    expect = np.zeros((512, 640), bool)
    expect[156:356, 220:420] = True
    np.testing.assert_array_equal(v.mask, expect)
    np.testing.assert_array_equal(v.depth > 0, expect)
    assert v.depth.max() == pytest.approx(3.0)  # 600 mm / 200
    half = load_scene(tmp_path / "scan1", "dtu", scale=0.5).views[vid]
    assert half.mask.shape == half.depth.shape == (256, 320)
    assert half.mask[78:178, 110:210].all() and half.mask.sum() == 100 * 100


def test_same_pixel_in_every_format(tmp_path):
    """One camera rig written in each format's own convention projects points identically."""
    cams = make_cameras(3)
    ims = rand_images(3)
    write_blender(tmp_path / "blender", cams, ims)
    write_nerfstudio(tmp_path / "ns", cams, ims, extra={"near": 2, "far": 6})
    write_llff(tmp_path / "llff", cams, ims, np.tile([2.0, 6.0], (3, 1)))
    write_colmap(tmp_path / "colmap", cams, ims, points=POINTS)
    scenes = {
        "blender": load_scene(tmp_path / "blender", "blender"),
        "nerfstudio": load_scene(tmp_path / "ns", "nerfstudio"),
        "llff": load_scene(tmp_path / "llff", "llff"),
        "colmap": load_scene(tmp_path / "colmap", "colmap"),
    }
    for i, c in enumerate(cams):
        ref_uv, ref_z = c.project(POINTS)
        assert np.all(ref_z > 0) and np.all((ref_uv >= 0) & (ref_uv <= [W - 1, H - 1]))
        for fmt, scene in scenes.items():
            v = list(scene.views.values())[i]
            uv, z = v.camera.project(POINTS)
            np.testing.assert_allclose(uv, ref_uv, atol=1e-9, err_msg=fmt)
            np.testing.assert_allclose(z, ref_z, atol=1e-9, err_msg=fmt)
            np.testing.assert_allclose(v.image, ims[i] / 255.0, atol=1e-6, err_msg=fmt)


@pytest.mark.parametrize("scale", [0.5, 0.25, 2.0])
def test_scale_keeps_pixel_centres(tmp_path, scale):
    K = np.array([[80.0, 0, 30.25], [0, 75.0, 25.5], [0, 0, 1]])
    cams = make_cameras(2, K=K)
    write_nerfstudio(tmp_path, cams, rand_images(2), extra={"near": 2, "far": 6})
    v = load_scene(tmp_path, "nerfstudio", scale=scale).views["frame_00000"]
    assert (v.camera.width, v.camera.height) == (round(W * scale), round(H * scale))
    assert v.image.shape == (round(H * scale), round(W * scale), 3)
    uv0, _ = cams[0].project(POINTS)
    uv1, _ = v.camera.project(POINTS)
    np.testing.assert_allclose(uv1, (uv0 + 0.5) * scale - 0.5, atol=1e-9)
    assert v.camera.K[0, 0] == pytest.approx(80.0 * scale)
    assert v.camera.K[0, 2] == pytest.approx((30.25 + 0.5) * scale - 0.5)


def test_scale_resamples_the_image_consistently(tmp_path):
    """A smooth image downsampled by 1/2 keeps its values at the pixel-centre-mapped positions."""
    cams = make_cameras(1, width=64, height=64, K=np.array([[F, 0, 32], [0, F, 32], [0, 0, 1]]))
    y, x = np.mgrid[0:64, 0:64]
    im = np.stack([x * 3, y * 3, (x + y)], -1).astype(np.uint8)
    write_nerfstudio(tmp_path, cams, [im], extra={"near": 2, "far": 6})
    v = load_scene(tmp_path, "nerfstudio", scale=0.5).views["frame_00000"]
    y2, x2 = np.mgrid[0:32, 0:32]
    # pixel (u', v') of the half image covers source centre ((u'+0.5)*2-0.5) = 2u'+0.5
    np.testing.assert_allclose(v.image[2:-2, 2:-2, 0] * 255, ((2 * x2 + 0.5) * 3)[2:-2, 2:-2], atol=0.6)
    np.testing.assert_allclose(v.image[2:-2, 2:-2, 1] * 255, ((2 * y2 + 0.5) * 3)[2:-2, 2:-2], atol=0.6)


def test_crop_and_resize_view_helpers():
    cams = make_cameras(1)
    view = View("a", np.random.default_rng(0).random((H, W, 3), dtype=np.float32), cams[0], mask=np.ones((H, W), bool))
    c = crop_view(view, 4, 6, 32, 32)
    assert c.image.shape == (32, 32, 3) and c.mask.shape == (32, 32)
    uv, _ = view.camera.project(POINTS)
    uvc, _ = c.camera.project(POINTS)
    np.testing.assert_allclose(uvc, uv - [4, 6], atol=1e-9)
    np.testing.assert_array_equal(c.image, view.image[6:38, 4:36])
    with pytest.raises(ValueError, match="outside"):
        crop_view(view, 40, 0, 32, 32)
    r = resize_view(view, 32, 24)
    assert r.image.shape == (24, 32, 3) and r.mask.all()


def test_get_views_by_name(tmp_path):
    write_blender(tmp_path, make_cameras(3), rand_images(3))
    scene = load_scene(tmp_path, "blender")
    assert [v.name for v in D.get_views(scene, "r_2,r_0")] == ["r_2", "r_0"]
    with pytest.raises(KeyError, match="available views: r_0, r_1, r_2"):
        D.get_views(scene, ["r_7"])


# ----------------------------------------------------------------------------- errors


def test_unknown_format_and_missing_paths(tmp_path):
    with pytest.raises(ValueError, match="unknown scene format"):
        load_scene(tmp_path, "ply")
    for fmt in D.FORMATS:
        with pytest.raises(FileNotFoundError):
            load_scene(tmp_path / "nope", fmt)
        with pytest.raises(FileNotFoundError):
            load_scene(tmp_path, fmt)  # empty folder


def test_bad_scale(tmp_path):
    write_blender(tmp_path, make_cameras(1), rand_images(1))
    for s in (0, -1, float("nan")):
        with pytest.raises(ValueError, match="scale"):
            load_scene(tmp_path, "blender", scale=s)


def test_malformed_dtu_camera_names_the_file(tmp_path):
    cams = make_cameras(2, K=np.array([[1400.0, 0, 320], [0, 1400, 256], [0, 0, 1]]), width=640, height=512)
    ids = write_dtu(tmp_path / "scan1", cams, rand_images(2, width=640, height=512))
    bad = tmp_path / "scan1" / "Cameras" / "train" / f"{int(ids[1]):08d}_cam.txt"
    bad.write_text("extrinsic\n1 0 0\n0 1 0\n")
    with pytest.raises(ValueError, match=bad.name):
        load_scene(tmp_path / "scan1", "dtu")
    bad.write_text(bad.read_text() + "\nintrinsic\n1 0 0 0 1 0 0 0 1\n")
    with pytest.raises(ValueError, match="extrinsic must have 16"):
        load_scene(tmp_path / "scan1", "dtu")


def test_dtu_rejects_wrong_image_size(tmp_path):
    cams = make_cameras(1, width=64, height=48)
    write_dtu(tmp_path / "scan1", cams, rand_images(1))
    with pytest.raises(ValueError, match="640x512"):
        load_scene(tmp_path / "scan1", "dtu")


def test_malformed_transforms_json(tmp_path):
    write_blender(tmp_path, make_cameras(1), rand_images(1))
    jf = tmp_path / "transforms_train.json"
    jf.write_text("{not json")
    with pytest.raises(ValueError, match="transforms_train.json"):
        load_scene(tmp_path, "blender")
    jf.write_text(json.dumps({"frames": []}))
    with pytest.raises(ValueError, match="camera_angle_x"):
        load_scene(tmp_path, "blender")
    jf.write_text(
        json.dumps(
            {"camera_angle_x": 0.7, "frames": [{"file_path": "./train/r_0", "transform_matrix": [[1, 0], [0, 1]]}]}
        )
    )
    with pytest.raises(ValueError, match="transform_matrix"):
        load_scene(tmp_path, "blender")


def test_bad_image_file(tmp_path):
    write_blender(tmp_path, make_cameras(1), rand_images(1))
    (tmp_path / "train" / "r_0.png").write_bytes(b"not a png")
    with pytest.raises(ValueError, match="r_0.png"):
        load_scene(tmp_path, "blender")


def test_malformed_llff(tmp_path):
    write_llff(tmp_path, make_cameras(2), rand_images(2), np.array([[1.0, 5.0], [1.0, 5.0]]))
    np.save(tmp_path / "poses_bounds.npy", np.zeros((2, 15)))
    with pytest.raises(ValueError, match="N x 17"):
        load_scene(tmp_path, "llff")
    (tmp_path / "poses_bounds.npy").write_bytes(b"garbage")
    with pytest.raises(ValueError, match="poses_bounds.npy"):
        load_scene(tmp_path, "llff")
    arr = np.zeros((3, 17))
    np.save(tmp_path / "poses_bounds.npy", arr)
    with pytest.raises(ValueError, match="3 poses but 2 images"):
        load_scene(tmp_path, "llff")


def test_malformed_colmap(tmp_path):
    write_colmap(tmp_path, make_cameras(2), rand_images(2), points=POINTS)
    cam_file = tmp_path / "sparse" / "0" / "cameras.txt"
    good = cam_file.read_text()
    cam_file.write_text(good.replace("PINHOLE", "THIN_PRISM_FISHEYE"))
    with pytest.raises(ValueError, match="THIN_PRISM_FISHEYE is not supported"):
        load_scene(tmp_path, "colmap")
    cam_file.write_text(good.replace("PINHOLE 64", "PINHOLE sixty-four"))
    with pytest.raises(ValueError, match="cameras.txt"):
        load_scene(tmp_path, "colmap")
    cam_file.write_text(good)
    img_file = tmp_path / "sparse" / "0" / "images.txt"
    img_file.write_text("1 1 0 0 0 0 0\n\n")
    with pytest.raises(ValueError, match="images.txt"):
        load_scene(tmp_path, "colmap")


# ----------------------------------------------------------------------------- real data

DATA = shared_data_dir()
needs_dtu = pytest.mark.skipif(
    DATA is None or not (DATA / "dtu_scan37").is_dir(),
    reason="real DTU scan37 not found: ../shared/data/dtu_scan37 (or $SCNERF_SHARED/data) is absent on this machine",
)
needs_lego = pytest.mark.skipif(
    DATA is None or not (DATA / "nerf_synthetic_lego").is_dir(),
    reason="real lego scene not found: ../shared/data/nerf_synthetic_lego "
    "(or $SCNERF_SHARED/data) is absent on this machine",
)


@pytest.fixture(scope="module")
def dtu_scene():
    return load_scene(DATA / "dtu_scan37", "dtu")


@pytest.fixture(scope="module")
def lego_scene():
    return load_scene(DATA / "nerf_synthetic_lego", "blender")


@needs_dtu
def test_real_dtu_scan37(dtu_scene):
    s = dtu_scene
    assert s.near == pytest.approx(2.125, abs=1e-12) and s.far == pytest.approx(4.525, abs=1e-12)
    assert len(s.views) == 20
    assert s.default_sources == ["25", "21", "33"] and s.default_targets == ["32", "24", "23", "44"]
    for name, v in s.views.items():
        assert v.image.shape == (512, 640, 3) and v.image.dtype == np.float32
        assert 0.0 <= v.image.min() and v.image.max() <= 1.0
        assert v.mask is not None and v.mask.shape == (512, 640) and v.mask.dtype == bool
        # scan37's object fills the lower middle of every view; the top rows are background
        assert v.mask[400:500, 200:440].mean() > 0.95, name
        assert not v.mask[:40].any(), name
        assert 0.2 < v.mask.mean() < 0.7, name
        assert np.allclose(v.camera.w2c[:3, :3] @ v.camera.w2c[:3, :3].T, np.eye(3), atol=1e-5)
    # view 25: file intrinsics x4, translation / 200
    K = s.views["25"].camera.K
    np.testing.assert_allclose(K[0], [361.541351 * 4, 0, 82.900696 * 4], atol=1e-9)
    np.testing.assert_allclose(
        s.views["25"].camera.w2c[:3, 3], [-294.210632 / 200, -402.820435 / 200, 247.354492 / 200], atol=1e-12
    )


@needs_dtu
def test_real_dtu_matches_idr_cameras(dtu_scene):
    """cameras_sphere.npz (world_mat = K[R|t] at 1600x1200, mm) agrees with the MVSNet cameras
    under MVSNet's 640x512 transform (u/2 - 80, v/2 - 44) to a hundredth of a pixel."""
    npz_path = DATA / "dtu_scan37" / "cameras_sphere.npz"
    if not npz_path.exists():
        pytest.skip(f"{npz_path} absent")
    cams = np.load(npz_path)
    ref = dtu_scene.views["25"].camera
    rng = np.random.default_rng(0)
    uv = np.stack([rng.uniform(100, 540, 64), rng.uniform(80, 430, 64)], 1)
    z = rng.uniform(2.3, 4.3, 64)
    pc = np.concatenate([(uv - ref.K[:2, 2]) / np.diag(ref.K)[:2] * z[:, None], z[:, None]], 1)
    c2w = np.linalg.inv(ref.w2c)
    X = pc @ c2w[:3, :3].T + c2w[:3, 3]
    for name, v in dtu_scene.views.items():
        P = cams[f"world_mat_{int(name)}"]
        q = np.concatenate([X / DTU_SCALE, np.ones((len(X), 1))], 1) @ P[:3].T
        expect = q[:, :2] / q[:, 2:] / 2 - [80, 44]
        got, zz = v.camera.project(X)
        assert np.all(zz > 0)
        np.testing.assert_allclose(got, expect, atol=0.01, err_msg=name)


@needs_dtu
def test_real_dtu_scaled(dtu_scene):
    s = load_scene(DATA / "dtu_scan37", "dtu", scale=0.5)
    v, full = s.views["32"], dtu_scene.views["32"]
    assert v.image.shape == (256, 320, 3) and v.mask.shape == (256, 320)
    assert v.camera.K[0, 0] == pytest.approx(full.camera.K[0, 0] * 0.5)
    assert v.camera.K[1, 2] == pytest.approx((full.camera.K[1, 2] + 0.5) * 0.5 - 0.5)
    np.testing.assert_array_equal(v.camera.w2c, full.camera.w2c)
    assert (s.near, s.far) == (pytest.approx(2.125), pytest.approx(4.525))
    assert abs(v.mask.mean() - full.mask.mean()) < 0.01


@needs_lego
def test_real_lego(lego_scene):
    s = lego_scene
    assert len(s.views) == 20
    assert s.near == 2.0 and s.far == 6.0 and s.background == (1.0, 1.0, 1.0)
    assert s.default_sources == ["r_6", "r_43", "r_33"]
    assert s.default_targets == ["r_63", "r_70", "r_18", "r_28"]
    for name in s.default_sources + s.default_targets:
        assert name in s.views
    f = 0.5 * 800 / math.tan(0.5 * 0.6911112070083618)
    for name, v in s.views.items():
        assert v.image.shape == (800, 800, 3)
        np.testing.assert_allclose(v.camera.K, [[f, 0, 400], [0, f, 400], [0, 0, 1]], rtol=1e-12)
        # transparent corners composite to white
        assert np.all(v.image[:5, :5] == 1.0), name
        # the object (world origin) is in front of the camera and projects inside the image
        uv, z = v.camera.project(np.zeros((1, 3)))
        assert 2.0 < z[0] < 6.0, name
        assert np.all((uv > 0) & (uv < 799)), name
        # ... and near the image centre, where the (non-white) object is
        assert np.all(np.abs(uv - 399.5) < 150), name
        u, vv = np.round(uv[0]).astype(int)
        assert v.image[vv - 40 : vv + 40, u - 40 : u + 40].mean() < 0.98, name
