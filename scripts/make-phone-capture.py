"""A phone-like capture made from a real posed scene, to try the `scnerf` client the way a phone
capture reaches it: portrait photos with lens distortion in instant-ngp's layout (transforms.json
with top-level fl_x, fl_y, cx, cy, w, h, k1, k2, p1, p2, aabb_scale, no depth range) or a COLMAP
folder (one SIMPLE_RADIAL or OPENCV camera, no points). Nothing of the scene is kept in the
repository; the capture is written where you say.

Each photo is what a camera with that lens, at the scene's pose, would have taken: the central
portrait crop of the scene's view, scaled to --size, distorted by the lens (for every photo pixel,
the undistorted ray by OpenCV's model, inverted by fixed-point steps, then the scene's image
sampled bilinearly there). The scene's field of view is narrower than a phone's (DTU's focal
length is 2.8 times its image height, LLFF's 1.1; a phone's main camera about 0.8 times the long
side), so the lens's coefficients are scaled to move pixels as far as the phone lens moves them on
a phone's field of view: k1 s^2, k2 s^4, p s, with s the ratio of the two focal lengths.

    scnerf info ../shared/data/llff_horns --json > /tmp/horns.json
    python scripts/make-phone-capture.py /tmp/horns.json /tmp/phone --layout instant-ngp
    scnerf eval /tmp/phone --holdout 8 --downscale 4

docs/results.md ("Lens distortion") has what undistortion gives on these.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from PIL import Image

#: A phone's main camera: focal length / the photo's long side.
PHONE_FOCAL = 0.8

LENSES = {
    # k1, k2, p1, p2 on a phone's field of view: mild pincushion, as COLMAP and instant-ngp write it
    "instant-ngp": (0.05, 0.01, 0.0005, -0.0003),
    "colmap-simple-radial": (0.058, 0.0, 0.0, 0.0),
    "colmap-opencv": (0.05, 0.01, 0.0005, -0.0003),
}


def on_this_view(lens, focal, long_side):
    """The phone lens's coefficients for a camera of `focal` (pixels), moving pixels as far."""
    k1, k2, p1, p2 = lens
    s = focal / (PHONE_FOCAL * long_side)
    return k1 * s**2, k2 * s**4, p1 * s, p2 * s


def distort(x, y, lens):
    k1, k2, p1, p2 = lens
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 * r2
    return x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x), y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y


def undistort(xd, yd, lens, steps=30):
    """OpenCV's fixed-point inverse of `distort` (converges for a mild lens)."""
    k1, k2, p1, p2 = lens
    x, y = xd.copy(), yd.copy()
    for _ in range(steps):
        r2 = x * x + y * y
        radial = 1 + k1 * r2 + k2 * r2 * r2
        dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        x, y = (xd - dx) / radial, (yd - dy) / radial
    return x, y


def bilinear(image, u, v):
    """`image` (H, W, 3) at pixel coordinates (u, v) (centres at integers); black outside."""
    h, w, _ = image.shape
    inside = (u >= 0) & (v >= 0) & (u <= w - 1) & (v <= h - 1)
    u, v = np.clip(u, 0, w - 1), np.clip(v, 0, h - 1)
    u0, v0 = np.minimum(np.floor(u).astype(int), w - 2), np.minimum(np.floor(v).astype(int), h - 2)
    tu, tv = (u - u0)[..., None], (v - v0)[..., None]
    top = image[v0, u0] * (1 - tu) + image[v0, u0 + 1] * tu
    bottom = image[v0 + 1, u0] * (1 - tu) + image[v0 + 1, u0 + 1] * tu
    return np.where(inside[..., None], top * (1 - tv) + bottom * tv, 0.0)


def phone_photo(image, k, size, lens):
    """The portrait photo of `size` a camera with the phone lens `lens` takes of the view `image`
    (intrinsics `k`), that photo's intrinsics (pixel centres at integers) and its lens's coefficients."""
    h, w, _ = image.shape
    crop = h * size[0] / size[1]  # the portrait crop's width
    x0 = (w - crop) / 2
    s = size[1] / h
    fx, fy = k["fx"] * s, k["fy"] * s
    cx, cy = (k["cx"] - x0 + 0.5) * s - 0.5, (k["cy"] + 0.5) * s - 0.5
    lens = on_this_view(lens, fx, max(size))
    v, u = np.mgrid[0 : size[1], 0 : size[0]].astype(float)
    x, y = undistort((u - cx) / fx, (v - cy) / fy, lens)
    photo = bilinear(image.astype(float), k["fx"] * x + k["cx"], k["fy"] * y + k["cy"])
    return np.clip(np.round(photo), 0, 255).astype(np.uint8), (fx, fy, cx, cy), lens


def opengl_c2w(w2c):
    c2w = np.linalg.inv(np.asarray(w2c, float))
    return c2w @ np.diag([1.0, -1.0, -1.0, 1.0])


def quaternion(r):
    """(w, x, y, z) of a rotation matrix."""
    w = np.sqrt(max(0.0, 1 + r[0, 0] + r[1, 1] + r[2, 2])) / 2
    x = np.copysign(np.sqrt(max(0.0, 1 + r[0, 0] - r[1, 1] - r[2, 2])) / 2, r[2, 1] - r[1, 2])
    y = np.copysign(np.sqrt(max(0.0, 1 - r[0, 0] + r[1, 1] - r[2, 2])) / 2, r[0, 2] - r[2, 0])
    z = np.copysign(np.sqrt(max(0.0, 1 - r[0, 0] - r[1, 1] + r[2, 2])) / 2, r[1, 0] - r[0, 1])
    return w, x, y, z


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("info", type=Path, help="`scnerf info SCENE --json` of the scene")
    parser.add_argument("out", type=Path)
    parser.add_argument("--layout", choices=sorted(LENSES), default="instant-ngp")
    parser.add_argument("--size", default="1080x1920", help="portrait WxH of the photos")
    args = parser.parse_args()
    size = tuple(int(n) for n in args.size.split("x"))
    info = json.loads(args.info.read_text())
    (args.out / "images").mkdir(parents=True, exist_ok=False)
    frames, images_txt, intrinsics = [], [], None
    for i, view in enumerate(info["views"]):
        image = np.asarray(Image.open(view["image"]).convert("RGB"))
        photo, intrinsics, lens = phone_photo(image, view["camera"]["intrinsics"], size, LENSES[args.layout])
        name = f"{i:04}.jpg"
        Image.fromarray(photo).save(args.out / "images" / name, quality=95)
        w2c = np.asarray(view["camera"]["pose"]["matrix"], float)
        frames.append({"file_path": f"images/{name}", "transform_matrix": opengl_c2w(w2c).tolist()})
        qw, qx, qy, qz = quaternion(w2c[:3, :3])
        t = w2c[:3, 3]
        images_txt.append(f"{i + 1} {qw} {qx} {qy} {qz} {t[0]} {t[1]} {t[2]} 1 {name}\n\n")
    fx, fy, cx, cy = intrinsics
    k1, k2, p1, p2 = lens
    if args.layout == "instant-ngp":
        # nerfstudio's and instant-ngp's pixel centres are at +0.5
        transforms = {"fl_x": fx, "fl_y": fy, "cx": cx + 0.5, "cy": cy + 0.5, "w": size[0], "h": size[1],
                      "k1": k1, "k2": k2, "p1": p1, "p2": p2, "aabb_scale": 4, "frames": frames}  # fmt: skip
        (args.out / "transforms.json").write_text(json.dumps(transforms, indent=1))
    else:
        sparse = args.out / "sparse" / "0"
        sparse.mkdir(parents=True)
        camera = (
            f"SIMPLE_RADIAL {size[0]} {size[1]} {fx} {cx + 0.5} {cy + 0.5} {k1}"
            if args.layout == "colmap-simple-radial"
            else f"OPENCV {size[0]} {size[1]} {fx} {fy} {cx + 0.5} {cy + 0.5} {k1} {k2} {p1} {p2}"
        )
        (sparse / "cameras.txt").write_text(f"1 {camera}\n")
        (sparse / "images.txt").write_text("".join(images_txt))
    print(f"wrote {len(frames)} views of {size[0]}x{size[1]} to {args.out} ({args.layout})")


if __name__ == "__main__":
    main()
