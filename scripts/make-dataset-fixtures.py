#!/usr/bin/env python3
"""Writes the small dataset fixtures of tests/fixtures/datasets/ that both the Rust readers of the
capture crate (capture/tests/readers.rs) and the Python loaders
(exporter/tests/data/test_dataset_fixtures.py) read, so the two cannot drift apart.

One folder per format (blender, nerfstudio, llff, colmap, colmap_binary, dtu), each with tiny
images and the cameras of a few views on a ring around the origin, plus the corner cases each
loader handles (frames without an image, declared sizes that differ from the image, duplicate
stems across splits, a pose that is rigid only to 3e-6, zero distortion, natural name order...).
Each folder except colmap_binary gets an expected.json written from what
``scnerf_export.data.datasets.load_scene`` returns for it; colmap_binary holds the colmap model in
COLMAP's binary form and must give colmap's expected cameras. metrics.json holds two fixed
images and the PSNR / SSIM of ``scnerf_export.evaluate.metrics`` for them.

Run from the repository root (deterministic: a second run rewrites the same bytes):

    PYTHONPATH=exporter .venv/bin/python scripts/make-dataset-fixtures.py
"""

from __future__ import annotations

import json
import math
import shutil
import struct
import sys
from pathlib import Path

import numpy as np
from PIL import Image

from scnerf_export.cameras import look_at
from scnerf_export.data.datasets import load_scene
from scnerf_export.evaluate import metrics

ROOT = Path(__file__).resolve().parents[1] / "tests" / "fixtures" / "datasets"
W, H = 8, 6
GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


def ring(n: int, radius: float, seed: int, arc: float = 2 * math.pi) -> list[np.ndarray]:
    """World-to-camera matrices (OpenCV) of n cameras spread over ``arc`` radians of a ring around
    the origin, looking near it."""
    rng = np.random.default_rng(seed)
    poses = []
    for i in range(n):
        a = arc * i / n + rng.uniform(-0.2, 0.2)
        eye = [radius * math.cos(a), radius * math.sin(a), radius * rng.uniform(0.2, 0.5)]
        poses.append(look_at(eye, rng.normal(scale=0.05 * radius, size=3)))
    return poses


def gl_c2w(w2c: np.ndarray) -> np.ndarray:
    return np.linalg.inv(w2c) @ GL_TO_CV


def rot_to_quat(r: np.ndarray) -> list[float]:
    """(qw, qx, qy, qz) of a rotation matrix (Shepperd's method)."""
    t = np.trace(r)
    if t > 0:
        s = math.sqrt(t + 1.0) * 2
        return [0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
    i = int(np.argmax(np.diag(r)))
    j, k = (i + 1) % 3, (i + 2) % 3
    s = math.sqrt(1.0 + r[i, i] - r[j, j] - r[k, k]) * 2
    q = [0.0] * 4
    q[0] = (r[k, j] - r[j, k]) / s
    q[1 + i] = 0.25 * s
    q[1 + j] = (r[j, i] + r[i, j]) / s
    q[1 + k] = (r[k, i] + r[i, k]) / s
    return q


def save_image(path: Path, seed: int, size=(W, H), mode="RGB") -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    channels = len(mode)
    arr = np.random.default_rng(seed).integers(0, 256, size=(size[1], size[0], channels), dtype=np.uint8)
    Image.fromarray(arr, mode).save(path)


def save_flat_image(path: Path, size: tuple[int, int], value: int) -> None:
    """A uniform image: DTU's 640x512 fixtures stay a few hundred bytes."""
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.new("RGB", size, (value, value // 2, 255 - value)).save(path)


def fresh(name: str) -> Path:
    d = ROOT / name
    if d.exists():
        shutil.rmtree(d)
    d.mkdir(parents=True)
    return d


def write_json(path: Path, data) -> None:
    path.write_text(json.dumps(data, indent=1) + "\n")


# ----------------------------------------------------------------------------- formats


def make_blender() -> dict[str, str]:
    d = fresh("blender")
    poses = ring(5, 4.0, seed=1)
    angle = 2 * math.atan(0.5 * W / 9.0)
    images = {}
    train = []
    for i in range(4):
        c2w = gl_c2w(poses[i])
        # nearly rigid poses, within the server's tolerance: r_1 passes datasets._invert_rigid's
        # allclose test (inverted by transposing), r_2 does not (a general inverse)
        if i == 1:
            c2w[:3, :3] *= 1 + 3e-6
        if i == 2:
            c2w[:3, 0] *= 1 + 5e-5
        train.append({"file_path": f"./train/r_{i}", "rotation": 0.1, "transform_matrix": c2w.tolist()})
        save_image(d / "train" / f"r_{i}.png", seed=10 + i, mode="RGBA")
        images[f"train/r_{i}"] = f"train/r_{i}.png"
    for i in (98, 99):  # listed, but the images are not in the folder
        train.append({"file_path": f"./train/r_{i}", "transform_matrix": gl_c2w(poses[0]).tolist()})
    write_json(d / "transforms_train.json", {"camera_angle_x": angle, "frames": train})
    # the same stem in another split: every name becomes split/stem
    val = [{"file_path": "./val/r_0.png", "transform_matrix": gl_c2w(poses[4]).tolist()}]
    save_image(d / "val" / "r_0.png", seed=20, mode="RGBA")
    images["val/r_0"] = "val/r_0.png"
    write_json(d / "transforms_val.json", {"camera_angle_x": angle, "camera_angle_y": angle * 0.8, "frames": val})
    return images


def make_nerfstudio() -> dict[str, str]:
    d = fresh("nerfstudio")
    poses = ring(5, 3.0, seed=2)
    frames, images = [], {}
    for i, w2c in enumerate(poses):
        rel = f"images/frame_{i + 1:05d}.png"
        fr = {"file_path": rel, "transform_matrix": gl_c2w(w2c).tolist()}
        if i == 1:  # per-frame intrinsics at the image's own size
            fr.update({"fl_x": 7.5, "fl_y": 7.0, "cx": 4.2, "cy": 2.9, "w": W, "h": H})
        frames.append(fr)
        if i != 3:  # frame 4's image is missing
            save_image(d / rel, seed=30 + i)
            images[f"frame_{i + 1:05d}"] = rel
    # top-level intrinsics declared at twice the size of the images on disk
    write_json(
        d / "transforms.json",
        {
            "camera_model": "OPENCV",
            "fl_x": 16.0,
            "fl_y": 15.0,
            "cx": 8.1,
            "cy": 5.9,
            "w": 2 * W,
            "h": 2 * H,
            "k1": 0.0,
            "k2": 0.0,
            "p1": 0.0,
            "p2": 0.0,
            "near_far": [0.5, 9.0],
            "frames": frames,
        },
    )
    return images


def make_llff() -> dict[str, str]:
    d = fresh("llff")
    # forward-facing, as LLFF captures are: cameras in a plane, looking along +y
    rng = np.random.default_rng(3)
    eyes = [np.array([x, 0.0, z]) for x, z in [(-0.3, 0.1), (0.25, 0.05), (0.0, -0.2), (0.3, -0.1)]]
    poses = [look_at(e, e * 0.2 + [0.0, 10.0, 0.0] + rng.normal(scale=0.1, size=3)) for e in eyes]
    rows, images = [], {}
    for i, w2c in enumerate(poses):
        c2w = np.linalg.inv(w2c)
        llff = np.stack([c2w[:3, 1], c2w[:3, 0], -c2w[:3, 2]], axis=1)  # [down, right, back]
        hwf = np.array([[4.0 * H], [4.0 * W], [28.0]])  # full resolution: 4x the images here
        m = np.concatenate([llff, c2w[:3, 3:4], hwf], axis=1)
        rows.append(np.concatenate([m.ravel(), [0.8 + 0.1 * i, 6.0 + i]]))
        name = f"IMG_{i:04d}"
        save_image(d / "images" / f"{name}.jpg", seed=40 + i)
        images[name] = f"images/{name}.jpg"
    np.save(d / "poses_bounds.npy", np.array(rows))
    return images


COLMAP_CAMERAS = [  # id, model, declared width, height, params (COLMAP: first pixel centre at 0.5)
    (1, "PINHOLE", W, H, [9.0, 8.5, 4.1, 3.2]),
    (2, "SIMPLE_PINHOLE", 2 * W, 2 * H, [18.0, 8.0, 6.0]),  # declared at twice the image size
    (3, "SIMPLE_RADIAL", W, H, [9.5, 4.0, 3.0, 0.0]),  # no distortion: usable as a pinhole
]
COLMAP_MODEL_IDS = {"SIMPLE_PINHOLE": 0, "PINHOLE": 1, "SIMPLE_RADIAL": 2}
# names in an order that only a natural sort puts right; img4 is listed but has no image file
COLMAP_IMAGES = [("img10.png", 1), ("img2.png", 2), ("img9.png", 3), ("img1.png", 1), ("img4.png", 2)]


def colmap_model(seed: int):
    poses = ring(len(COLMAP_IMAGES), 3.0, seed=seed)
    rng = np.random.default_rng(seed + 100)
    points = []
    for k in range(24):
        xyz = rng.normal(scale=0.6, size=3)
        track = [] if k == 5 else sorted(rng.choice(len(COLMAP_IMAGES), size=2, replace=False) + 1)
        points.append((k + 1, xyz, track))
    return poses, points


def make_colmap() -> dict[str, str]:
    d = fresh("colmap")
    poses, points = colmap_model(seed=4)
    m = d / "sparse" / "0"
    m.mkdir(parents=True)
    cams = ["# Camera list with one line of data per camera:", "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]"]
    cams += [
        f"{cid} {model} {w} {h} " + " ".join(repr(float(p)) for p in params)
        for cid, model, w, h, params in COLMAP_CAMERAS
    ]
    (m / "cameras.txt").write_text("\n".join(cams) + "\n")
    lines = ["# Image list with two lines of data per image:"]
    images = {}
    for i, ((name, cid), w2c) in enumerate(zip(COLMAP_IMAGES, poses)):
        q = rot_to_quat(w2c[:3, :3])
        t = w2c[:3, 3]
        lines.append(" ".join([str(i + 1), *(repr(float(x)) for x in [*q, *t]), str(cid), name]))
        lines.append("" if i % 2 else "1.5 2.5 -1")  # the 2D points line may be empty
        if name != "img4.png":
            save_image(d / "images" / name, seed=50 + i)
            images[name[:-4]] = f"images/{name}"
    (m / "images.txt").write_text("\n".join(lines) + "\n")
    pts = ["# 3D point list with one line of data per point:"]
    for pid, xyz, track in points:
        tr = " ".join(f"{img} {j}" for j, img in enumerate(track))
        pts.append(f"{pid} " + " ".join(repr(float(x)) for x in xyz) + f" 128 128 128 0.5 {tr}".rstrip())
    (m / "points3D.txt").write_text("\n".join(pts) + "\n")
    return images


def make_colmap_binary() -> None:
    """The colmap fixture's model in COLMAP's binary form (reconstruction_io.cc), same images."""
    d = fresh("colmap_binary")
    shutil.copytree(ROOT / "colmap" / "images", d / "images")
    poses, points = colmap_model(seed=4)
    m = d / "sparse" / "0"
    m.mkdir(parents=True)
    with open(m / "cameras.bin", "wb") as f:
        f.write(struct.pack("<Q", len(COLMAP_CAMERAS)))
        for cid, model, w, h, params in COLMAP_CAMERAS:
            f.write(struct.pack("<IiQQ", cid, COLMAP_MODEL_IDS[model], w, h))
            f.write(struct.pack(f"<{len(params)}d", *params))
    with open(m / "images.bin", "wb") as f:
        f.write(struct.pack("<Q", len(COLMAP_IMAGES)))
        for i, ((name, cid), w2c) in enumerate(zip(COLMAP_IMAGES, poses)):
            f.write(struct.pack("<I4d3dI", i + 1, *rot_to_quat(w2c[:3, :3]), *w2c[:3, 3], cid))
            f.write(name.encode() + b"\0")
            pts2d = [] if i % 2 else [(1.5, 2.5, -1)]
            f.write(struct.pack("<Q", len(pts2d)))
            for x, y, pid in pts2d:
                f.write(struct.pack("<ddq", x, y, pid))
    with open(m / "points3D.bin", "wb") as f:
        f.write(struct.pack("<Q", len(points)))
        for pid, xyz, track in points:
            f.write(struct.pack("<Q3d3BdQ", pid, *xyz, 128, 128, 128, 0.5, len(track)))
            for j, img in enumerate(track):
                f.write(struct.pack("<II", int(img), j))


def make_dtu() -> dict[str, str]:
    d = fresh("dtu")
    poses = ring(5, 800.0, seed=5, arc=math.pi / 2)  # millimetres, on one side as DTU's cameras
    images = {}
    for vid, w2c in zip([0, 1, 2, 3, 9], poses):
        depth = "425.0 2.5" if vid != 2 else "400.0 2.6"
        K = [[90.0, 0.0, 80.2], [0.0, 89.5, 63.7], [0.0, 0.0, 1.0]]  # at 1/4 of 640x512
        text = "extrinsic\n" + "\n".join(" ".join(f"{x:.6f}" for x in row) for row in w2c)
        text += "\n\nintrinsic\n" + "\n".join(" ".join(f"{x:.6f}" for x in row) for row in K) + f"\n\n{depth}\n"
        (d / "Cameras" / "train").mkdir(parents=True, exist_ok=True)
        (d / "Cameras" / "train" / f"{vid:08d}_cam.txt").write_text(text)
        if vid != 9:  # camera 9 has no image
            rel = f"Rectified/scan1_train/rect_{vid + 1:03d}_3_r5000.png"
            save_flat_image(d / rel, (640, 512), 40 * vid)
            images[str(vid)] = rel
    return images


# ----------------------------------------------------------------------------- expected values


def expected(folder: str, fmt: str, images: dict[str, str], **kwargs) -> None:
    """What the Python loader makes of the folder, for both test suites to compare with."""
    scene = load_scene(ROOT / folder, fmt, **kwargs)
    views = []
    for name, view in scene.views.items():
        cam = view.camera
        views.append(
            {
                "name": name,
                "image": images[name],
                "width": cam.width,
                "height": cam.height,
                "K": cam.K.tolist(),
                "w2c": cam.w2c.tolist(),
            }
        )
    write_json(
        ROOT / folder / "expected.json",
        {
            "format": fmt,
            "near": scene.near,
            "far": scene.far,
            "background": list(scene.background),
            "views": views,
        },
    )


def make_metrics() -> None:
    """Two fixed 16x13 RGB images (a smooth pattern and a perturbed copy) and their metrics."""
    y, x = np.mgrid[0:13, 0:16].astype(np.float64)
    gt = np.stack([(np.sin(x / 3 + c) * np.cos(y / 4 - c) + 1) / 2 for c in range(3)], axis=-1)
    pred = np.clip(gt + 0.08 * np.sin(7 * x + 3 * y)[..., None] * np.array([1.0, -0.5, 0.25]), 0, 1)
    (ROOT / "metrics.json").write_text(
        json.dumps(
            {
                "shape": list(gt.shape),
                "psnr": metrics.psnr(pred, gt),
                "ssim": metrics.ssim(pred, gt),
                "gt": gt.ravel().tolist(),
                "pred": pred.ravel().tolist(),
            }
        )
        + "\n"
    )


def main() -> int:
    ROOT.mkdir(parents=True, exist_ok=True)
    expected("blender", "blender", make_blender())
    expected("nerfstudio", "nerfstudio", make_nerfstudio())
    expected("llff", "llff", make_llff())
    expected("colmap", "colmap", make_colmap())
    make_colmap_binary()
    expected("dtu", "dtu", make_dtu())
    make_metrics()
    print(f"wrote {ROOT}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
