#!/usr/bin/env python3
"""Writes tests/fixtures/rules/: the rules that both the Rust crates and the Python packages
compute, as cases and the answers of the Python side. Each side's tests check its own copy of a
rule against the same file, so a rule changed on one side alone fails that side's tests.

- chunks.json: rays per renderer run (server/src/pipeline/chunks.rs, ChunkPolicy;
  exporter/scnerf_export/runtime/chunks.py), full runs and guided sampling's fine runs.
  Read by chunks.rs's tests and exporter/tests/runtime/test_chunks.py.
- graph_contract.json: every graph's inputs and outputs (name, whether every bundle declares it,
  shape: fixed sizes and named axes) for the default bundle's config and the parity bundle's
  (server/src/bundle/contract.rs, expected_io; exporter/scnerf_export/export/bundle.py,
  graph_contract). Read by server/src/bundle/tests.rs and exporter/tests/export/test_graph_contract.py.
- image_files.json: which file names are images, which files of a folder are its images, a
  capture's image sets (images/, images_N/) and which one a pick takes (capture/src/image_sets.rs
  and readers/names.rs; exporter/scnerf_export/data/scene.py and dataparsers/llff.py, and the
  Python client's captures.py). Read by capture/tests/rules.rs and
  exporter/tests/data/test_rule_fixtures.py.
- cameras.json: the API's pose conventions (world-to-camera or camera-to-world, OpenCV or OpenGL
  axes) to the canonical OpenCV world-to-camera, look_at and a camera resized
  (capture/src/camera.rs; exporter/scnerf_export/cameras.py). Read by capture/tests/rules.rs and
  exporter/tests/data/test_rule_fixtures.py.

Run from the repository root (deterministic: a second run rewrites the same bytes):

    PYTHONPATH=exporter .venv/bin/python scripts/make-rule-fixtures.py
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

import numpy as np
from PIL import Image

from scnerf_export.cameras import OPENGL_TO_OPENCV, Camera, canonical_w2c, look_at, rank_sources
from scnerf_export.data import depth_range
from scnerf_export.data.dataparsers.llff import LlffParser
from scnerf_export.data.scene import is_image, list_images
from scnerf_export.export.bundle import graph_contract
from scnerf_export.export.manifest import Manifest
from scnerf_export.runtime.chunks import (
    BYTES_PER_SAMPLE,
    DEFAULT_MAX_RAYS,
    DEFAULT_MEMORY_MB,
    GUIDED_BYTES_PER_RAY,
    fine_rays_per_run,
    rays_per_run,
)

REPO = Path(__file__).resolve().parents[1]
ROOT = REPO / "tests" / "fixtures" / "rules"


def dumps(value, depth: int = 0) -> str:
    """JSON indented by one space a level, with every list or object that fits in 100 characters
    on one line."""
    flat = json.dumps(value)
    if not isinstance(value, (list, dict)) or len(flat) + depth <= 100:
        return flat
    pad, inner = " " * depth, " " * (depth + 1)
    if isinstance(value, list):
        items = [inner + dumps(v, depth + 1) for v in value]
        return "[\n" + ",\n".join(items) + "\n" + pad + "]"
    items = [f"{inner}{json.dumps(k)}: {dumps(v, depth + 1)}" for k, v in value.items()]
    return "{\n" + ",\n".join(items) + "\n" + pad + "}"


def write(name: str, data: dict) -> None:
    (ROOT / name).write_text(dumps(data) + "\n")


def chunks() -> dict:
    full = [(128, 1024, 512), (48, 1024, 512), (128, 4096, 4096), (1, 4096, 4096), (128, 0, 4096)]
    full += [(0, 1024, 512), (32, 256, 100), (64, 100, 10000), (128, 1024, 0)]
    fine = [(8, 128, 1024, 512), (128, 128, 1024, 512), (8, 128, 0, 512), (12, 128, 1024, 512)]
    fine += [(32, 128, 1024, 512), (16, 48, 1024, 512), (0, 128, 1024, 512), (8, 128, 1024, 0)]
    return {
        "what": "rays per renderer run: memory_mb << 20 bytes of budget, at most max_rays (a fine run: as "
        "many points as max_rays x full_samples), at least one",
        "bytes_per_sample": BYTES_PER_SAMPLE,
        "guided_bytes_per_ray": GUIDED_BYTES_PER_RAY,
        "default": {"max_rays": DEFAULT_MAX_RAYS, "memory_mb": DEFAULT_MEMORY_MB},
        "rays_per_chunk": [
            {"samples": s, "memory_mb": mb, "max_rays": cap, "rays": rays_per_run(s, mb, cap)} for s, mb, cap in full
        ],
        "fine_rays_per_chunk": [
            {
                "samples": s,
                "full_samples": f,
                "memory_mb": mb,
                "max_rays": cap,
                "rays": fine_rays_per_run(s, f, mb, cap),
            }
            for s, f, mb, cap in fine
        ],
    }


def graph_contracts() -> dict:
    configs = []
    for name, bundle in (("default", "bundles/default"), ("parity", "tests/fixtures/parity/bundle")):
        manifest = json.loads((REPO / bundle / "manifest.json").read_text())
        cfg = Manifest.load(REPO / bundle).config
        configs.append({"name": name, "bundle": bundle, "config": manifest["config"], "graphs": graph_contract(cfg)})
    return {
        "what": "each graph's inputs and outputs for a config: name, whether every bundle's graph declares "
        "it, shape (integers fixed, strings named dynamic axes)",
        "configs": configs,
    }


# File names, and whether each is an image by its extension and an image of its folder.
NAMES = [
    "IMG.Png",
    "a.JPG",
    "b.jpeg",
    "c.JPEG",
    "d.png",
    "e.jPeG",
    ".x.png",
    "._a.jpg",
    ".png",
    "notes.txt",
    "poses_bounds.npy",
    "transforms.json",
    "f.gif",
    "g.tif",
    "h.webp",
    "i.png.txt",
    "png",
    "j.",
    "k.jpg.bak",
]

# Captures: every file with its image size (null: not an image's bytes), the picks to make.
CAPTURES = [
    {
        "name": "every set and what is not one",
        "files": {
            "poses_bounds.npy": None,
            "images/IMG_0001.JPG": [64, 48],
            "images/IMG_0002.JPG": [60, 40],
            "images/._IMG_0001.JPG": [4, 3],
            "images/notes.txt": None,
            "images_2/IMG_0001.png": [32, 24],
            "images_2/IMG_0002.png": [32, 24],
            "images_4/IMG_0001.Png": [16, 12],
            "images_4/IMG_0002.Png": [16, 12],
            "images_1/a.png": [64, 48],
            "images_04/a.png": [16, 12],
            "images_x/a.png": [8, 6],
            "Images_2/a.png": [32, 24],
            "imgs_2/a.png": [32, 24],
            "images_8/.x.png": [8, 6],
            "images_8/readme.txt": None,
            "images_16": None,
        },
        "picks": [{"fit": n} for n in (3072, 3071, 768, 767, 192, 100)]
        + [{"downscale": n} for n in (0, 1, 2, 4, 3, 8, 16)],
    },
    {
        "name": "no sets",
        "files": {
            "poses_bounds.npy": None,
            "photos/a.png": [8, 6],
            "images_1/a.png": [8, 6],
            "images_02/a.png": [8, 6],
        },
        "picks": [{"fit": 100}, {"downscale": 1}, {"downscale": 2}],
    },
    {
        "name": "only a downscaled set",
        "files": {"poses_bounds.npy": None, "images_4/b.PNG": [16, 12], "images_4/a.jpg": [20, 10]},
        "picks": [{"fit": 200}, {"fit": 199}, {"downscale": 4}, {"downscale": 1}],
    },
]


def build(root: Path, files: dict) -> None:
    """The capture's files under ``root``: PNG bytes of each size, a byte for the others."""
    for rel, size in files.items():
        path = root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        if size is None:
            path.write_bytes(b"x")
        else:
            Image.new("RGB", tuple(size), (200, 100, 50)).save(path, format="PNG")


def image_files() -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "names"
        build(folder, dict.fromkeys(NAMES))
        listed = {p.name for p in list_images(folder)}
        names = []
        for name in NAMES:
            image = name in listed
            names.append({"name": name, "image_extension": is_image(Path(name)), "image": image})
        cases = [dict(case, **capture_answers(Path(tmp) / f"capture_{i}", case)) for i, case in enumerate(CAPTURES)]
    return {
        "what": "names: an image by its extension (png, jpg, jpeg in any case), and an image of its folder "
        "(not hidden either); captures: each folder's images in order, the image sets largest first with "
        "their first image's size, and the set each pick takes (fits: its images within the limit)",
        "names": names,
        "captures": cases,
    }


def capture_answers(root: Path, case: dict) -> dict:
    build(root, case["files"])
    folders = sorted({rel.split("/")[0] for rel in case["files"] if "/" in rel})
    images = {f: [p.name for p in list_images(root / f)] for f in folders}
    count = len(images.get("images", []))
    # The sets and the set each pick takes are the capture crate's alone (the clients ask the
    # server, POST /v1/captures/plan): kept from the fixture, which capture/tests/rules.rs checks.
    kept = next(
        c
        for c in json.loads((REPO / "tests/fixtures/rules/image_files.json").read_text())["captures"]
        if c["name"] == case["name"]
    )
    for pick in kept["picks"]:
        if pick.get("downscale", 0) > 1 and count:
            llff = LlffParser._downscaled_set(root, 1 / pick["downscale"], count)
            assert (llff[0].parent.name if llff else None) == pick.get("set"), "the LLFF parser picks another set"
    return {
        "images": images,
        "sets": kept["sets"],
        "picks": kept["picks"],
    }


def cameras() -> dict:
    eyes = [([1.0, 2.0, 3.0], [0.0, 0.5, 0.0]), ([-2.5, 0.4, 1.2], [0.1, -0.2, 0.3]), ([0.3, -3.0, 0.8], [0, 0, 0])]
    poses = []
    for eye, target in eyes:
        w2c_cv = look_at(eye, target)
        c2w_cv = np.linalg.inv(w2c_cv)
        c2w_gl = c2w_cv @ OPENGL_TO_OPENCV
        w2c_gl = np.linalg.inv(c2w_gl)
        for matrix, kind, axes in (
            (w2c_cv, "world_to_camera", "opencv"),
            (c2w_cv, "camera_to_world", "opencv"),
            (c2w_gl, "camera_to_world", "opengl"),
            (w2c_gl, "world_to_camera", "opengl"),
        ):
            poses.append((matrix, kind, axes))
    # As a transforms file holds a pose: float32, rigid only to ~1e-7.
    poses.append((poses[-2][0].astype(np.float32).astype(np.float64), "camera_to_world", "opengl"))
    looks = [(eye, target, [0.0, 0.0, 1.0]) for eye, target in eyes] + [([0.0, 0.0, 4.0], [1.0, 0.2, 0.0], [0, 1, 0])]
    resizes = [
        ((800, 800, 1111.1, 1111.1, 400.0, 400.0), (200, 200)),
        ((640, 512, 600.0, 610.0, 319.5, 255.5), (320, 256)),
    ]
    resizes += [
        ((4032, 3024, 3000.0, 3000.0, 2016.0, 1512.0), (504, 378)),
        ((101, 77, 90.0, 91.0, 50.0, 38.0), (50, 38)),
    ]
    return {
        "what": "poses: a matrix in one of the API's conventions and its canonical (OpenCV world-to-camera) "
        "form; look_at: the world-to-camera of a camera at eye looking at target, up up in the image; "
        "resized: a camera resampled to another size (pixel centres stay at integers)",
        "poses": [
            {"matrix": m.tolist(), "kind": kind, "axes": axes, "w2c": canonical_w2c(m, kind, axes).tolist()}
            for m, kind, axes in poses
        ],
        "look_at": [
            {
                "eye": list(map(float, e)),
                "target": list(map(float, t)),
                "up": list(map(float, u)),
                "w2c": look_at(e, t, u).tolist(),
            }
            for e, t, u in looks
        ],
        "resized": [resized(*case) for case in resizes],
    }


def resized(camera: tuple, size: tuple[int, int]) -> dict:
    w, h, fx, fy, cx, cy = camera
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    r = Camera(K, np.eye(4), w, h).resized(*size)
    before = {"width": w, "height": h, "fx": fx, "fy": fy, "cx": cx, "cy": cy}
    after = {"width": r.width, "height": r.height, "fx": r.K[0, 0], "fy": r.K[1, 1], "cx": r.K[0, 2], "cy": r.K[1, 2]}
    return {"camera": before, "resized": after}


def cameras_looking_at(eyes, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)) -> list[Camera]:
    return [Camera(np.eye(3), look_at(eye, target, up), 8, 6) for eye in eyes]


def placed(rotation, centre) -> Camera:
    """A camera of rotation ``rotation`` (world-to-camera) whose centre is ``centre``."""
    w2c = np.eye(4)
    w2c[:3, :3] = rotation
    w2c[:3, 3] = -np.asarray(rotation, dtype=np.float64) @ np.asarray(centre, dtype=np.float64)
    return Camera(np.eye(3), w2c, 8, 6)


def forward_grid(half_width: float, distance: float = 10.0) -> list[Camera]:
    """3 x 3 cameras on a plane at ``distance`` from the origin, all looking at it: the wider the
    grid, the more the axes spread (about (half_width / distance)^2)."""
    eyes = [(x * half_width, distance, z * half_width) for x in (-1, 0, 1) for z in (-1, 0, 1)]
    return cameras_looking_at(eyes)


def depth_rigs() -> list[tuple[str, list[Camera]]]:
    elevation = 0.5
    ring = [
        4 * np.array([np.cos(a) * np.cos(elevation), np.sin(a) * np.cos(elevation), np.sin(elevation)])
        for a in np.arange(8) * np.pi / 4
    ]
    arc = [(3 * np.sin(a), -3 * np.cos(a), 0.8) for a in np.radians([-25, -12, 0, 12, 25])]
    # Each on the line from the origin to its ring position, looking away from the origin.
    outwards = [placed(look_at((0, 0, 0), eye)[:3, :3], 0.5 * eye) for eye in ring[:4]]
    inwards = cameras_looking_at(ring[:3])
    away = placed(look_at((0, 0, 0), ring[5])[:3, :3], ring[5])  # on a line through the point, facing out
    return [
        ("an object seen from around it (lego)", cameras_looking_at(ring)),
        ("an object seen from one side (DTU)", cameras_looking_at(arc, target=(0.0, 0.0, 0.2))),
        ("forward-facing (LLFF)", forward_grid(1.5)),
        ("forward-facing, just below the object spread", forward_grid(1.9)),
        ("forward-facing, just above the object spread: an object", forward_grid(2.05)),
        ("forward-facing, just above the least spread", forward_grid(0.92)),
        ("forward-facing, just below the least spread: no range", forward_grid(0.84)),
        ("parallel axes: no point", [placed(np.eye(3), (x, y, 0.0)) for x in (-1, 0, 1) for y in (-1, 0, 1)]),
        ("looking outwards: the point is behind them all", outwards),
        ("one of four faces away: its depth is left out", inwards + [away]),
        ("two of four face away: the point is in front of no more than half", inwards[:2] + [away, away]),
        ("one camera", cameras_looking_at(ring[:1])),
        ("no camera", []),
    ]


def depth_ranges() -> dict:
    rigs = []
    for name, cameras in depth_rigs():
        meet = depth_range.convergence(cameras)
        poses = depth_range.from_poses(cameras)
        rigs.append(
            {
                "name": name,
                "w2c": [c.w2c.tolist() for c in cameras],
                "convergence": None if meet is None else {"point": meet[0].tolist(), "spread": meet[1]},
                "range": None if poses is None else list(poses),
            }
        )
    return {
        "what": "the depth range from the poses: the point nearest to every optical axis and the axes' spread "
        "(none when they spread by 0.01 or less, or the point is in front of no more than half the cameras); "
        "near = 0.4 x the least depth of the point in front of a camera, far = 1.6 x the largest (spread over "
        "0.05: an object seen from around it) or 8 x (a forward-facing capture)",
        "rigs": rigs,
    }


def source_rankings() -> dict:
    identity = np.eye(3)
    back = np.diag([1.0, -1.0, -1.0])  # looks along -z
    side = np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])  # looks along +x: 90 degrees
    rolled = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # still along +z
    rig = [
        placed(identity, (2, 0, 0)),
        placed(identity, (0, 2, 0)),
        placed(back, (1, 0, 0)),
        placed(side, (0, 0, 1)),
        placed(identity, (0, 0, -3)),
        placed(identity, (-1, 1, 0)),
        placed(rolled, (1, -1, 0)),
        placed(identity, (0, -2, 0)),
        placed(back, (0.5, 0, 0)),
    ]
    grid = [placed(identity, (x, y, 0)) for y in (-1, 0, 1) for x in (-1, 0, 1)]
    eyes = [(4 * np.cos(a), 4 * np.sin(a), 1.0 + 0.1 * i) for i, a in enumerate(np.arange(12) * 0.5)]
    ring = cameras_looking_at(eyes)
    cases = [
        ("ties, views facing away and one at 90 degrees", placed(identity, (0, 0, 0)), rig),
        ("a grid: ties go to the lower index", placed(identity, (0, 0, 0)), grid),
        ("a ring around an object: the far side is left out", ring[0], ring[1:]),
        ("no candidates", ring[0], []),
    ]
    return {
        "what": "source ranking: candidates by the distance of their centre to the target's, nearest first, "
        "ties to the lower index; those whose optical axis makes 90 degrees or more with the target's are left out",
        "cases": [
            {
                "name": name,
                "target": target.w2c.tolist(),
                "candidates": [c.w2c.tolist() for c in candidates],
                "ranked": rank_sources(target, candidates),
            }
            for name, target, candidates in cases
        ],
    }


def main() -> int:
    ROOT.mkdir(parents=True, exist_ok=True)
    write("chunks.json", chunks())
    write("graph_contract.json", graph_contracts())
    write("image_files.json", image_files())
    write("cameras.json", cameras())
    write("depth_range.json", depth_ranges())
    write("source_ranking.json", source_rankings())
    print(f"wrote {ROOT}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
