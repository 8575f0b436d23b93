"""Lens distortion in the Python readers (scnerf_export.data.lens): photos are resampled to the
pinhole camera the Rust readers send them as. The cameras of
capture/tests/fixtures/undistort/undistort.json (OpenCV's numbers, which capture/tests/undistort.rs
holds the Rust rule to) through the COLMAP reader, and the pixels of an undistorted photo against
the lens model written out here."""

import json
import warnings

import numpy as np
import pytest
from PIL import Image

from scnerf_export.data import lens
from scnerf_export.data.dataparsers.colmap import _camera
from scnerf_export.data.datasets import load_scene

from conftest import REPO

FIXTURE = json.loads((REPO / "capture" / "tests" / "fixtures" / "undistort" / "undistort.json").read_text())
PERSPECTIVE = [case for case in FIXTURE["cases"] if "FISHEYE" not in case["model"]]
NEAR_FAR = {"near": 1.0, "far": 5.0}


def ramp(width: int, height: int) -> np.ndarray:
    """A photo whose red is its column and green its row, scaled to [0, 1]."""
    u, v = np.meshgrid(np.arange(width) / (width - 1), np.arange(height) / (height - 1))
    return np.stack([u, v, np.full_like(u, 0.5)], axis=-1).astype(np.float32)


def save(image: np.ndarray, path):
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray((image * 255).round().astype(np.uint8)).save(path)


def colmap_capture(root, model: str, params: list[float], width: int, height: int):
    save(ramp(width, height), root / "images" / "0.png")
    (root / "cameras.txt").write_text(f"1 {model} {width} {height} " + " ".join(map(repr, params)) + "\n")
    (root / "images.txt").write_text("1 1 0 0 0 0 0 0 1 0.png\n\n")
    return root


def nerfstudio_capture(root, coefficients: dict, width=72, height=128):
    save(ramp(width, height), root / "images" / "0.png")
    frame = {"file_path": "images/0.png", "transform_matrix": np.eye(4).tolist()}
    intrinsics = {"fl_x": 60.0, "fl_y": 61.0, "cx": 36.0, "cy": 64.0, "w": width, "h": height}
    data = {"camera_model": "OPENCV", **intrinsics, **coefficients, **NEAR_FAR, "frames": [frame]}
    (root / "transforms.json").write_text(json.dumps(data))
    return root


def photo_position(K: np.ndarray, coefficients: np.ndarray, pinhole: np.ndarray, u, v):
    """Where pixel (u, v) of the pinhole image lies in the photo: OpenCV's perspective model,
    k1 k2 p1 p2 k3, written out."""
    k1, k2, p1, p2, k3 = coefficients[:5]
    x, y = (u - pinhole[0, 2]) / pinhole[0, 0], (v - pinhole[1, 2]) / pinhole[1, 1]
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return K[0, 0] * xd + K[0, 2], K[1, 1] * yd + K[1, 2]


def colmap_lens(case):
    """K, size and distortion of a fixture case's camera as the COLMAP reader reads them."""
    record = (1, case["model"], case["width"], case["height"], case["params"], "fixture")
    return _camera(record, ignore_distortion=False, warned=set())


@pytest.mark.parametrize("case", FIXTURE["cases"], ids=[c["model"] for c in FIXTURE["cases"]])
def test_the_undistortion_maps_are_opencvs_for_every_colmap_lens(case):
    K, width, height, distortion = colmap_lens(case)
    assert distortion.fisheye == ("FISHEYE" in case["model"])
    map_x, map_y = distortion.maps(K, np.array(case["map_k"]), width, height)
    u, v, x, y = np.array(case["map"]).T
    u, v = u.astype(int), v.astype(int)
    np.testing.assert_allclose(map_x[v, u], x, atol=1e-3)
    np.testing.assert_allclose(map_y[v, u], y, atol=1e-3)


@pytest.mark.parametrize("case", PERSPECTIVE, ids=[c["model"] for c in PERSPECTIVE])
def test_a_distorted_colmap_camera_loads_as_the_largest_rectangle_opencv_gives(tmp_path, case):
    """To the Rust rule's tolerance of OpenCV's camera (capture/tests/undistort.rs): the border is
    sampled more finely than OpenCV samples it."""
    colmap_capture(tmp_path, case["model"], case["params"], case["width"], case["height"])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        view = load_scene(tmp_path, "colmap", **NEAR_FAR).views["0"]
    got, want = view.camera.K, np.array(case["new_k_largest_rectangle"])
    np.testing.assert_allclose(np.diag(got)[:2], np.diag(want)[:2], rtol=1e-3)
    np.testing.assert_allclose(got[:2, 2], want[:2, 2], atol=0.05)
    assert view.image.shape == (case["height"], case["width"], 3)


@pytest.mark.parametrize("model", ["OPENCV", "OPENCV_FISHEYE"])
def test_every_pixel_of_the_pinhole_image_sees_the_photo_and_the_rectangle_is_the_largest(tmp_path, model):
    case = next(c for c in FIXTURE["cases"] if c["model"] == model)
    K, width, height, distortion = colmap_lens(case)
    map_x, map_y = distortion.maps(K, lens.pinhole_for(K, distortion, width, height), width, height)
    margin = np.minimum.reduce([map_x + 0.5, width - 0.5 - map_x, map_y + 0.5, height - 0.5 - map_y])
    assert margin.min() >= -1e-3, "a pixel of the pinhole image lies outside the photo"
    edges = np.concatenate([margin[0], margin[-1], margin[:, 0], margin[:, -1]])
    assert edges.min() <= 0.6, "a larger rectangle would still see the photo"


def test_each_undistorted_pixel_is_the_photo_where_the_lens_puts_it():
    width, height = 72, 128
    K = np.array([[58.0, 0.0, 36.0], [0.0, 61.0, 62.5], [0.0, 0.0, 1.0]])
    distortion = lens.perspective(k1=-0.09, k2=0.02, p1=0.001, p2=-0.0015, k3=0.004)
    image, pinhole = lens.undistort(ramp(width, height), K, distortion, background=(1.0, 0.0, 1.0))
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    x, y = photo_position(K, distortion.coefficients, pinhole, u, v)
    inside = (x >= 0) & (x <= width - 1) & (y >= 0) & (y <= height - 1)
    assert inside.mean() > 0.99, "the largest rectangle of valid pixels fills almost nothing"
    np.testing.assert_allclose(image[..., 0][inside], (x / (width - 1))[inside], atol=1e-3)
    np.testing.assert_allclose(image[..., 1][inside], (y / (height - 1))[inside], atol=1e-3)
    assert np.abs(x - u).max() > 1.0, "the lens moves pixels: the check above would hold for a copy"


def test_a_lens_that_cannot_be_inverted_over_the_image_is_refused(tmp_path):
    colmap_capture(tmp_path, "SIMPLE_RADIAL", [60.0, 36.0, 64.0, -3.0], 72, 128)
    with pytest.raises(ValueError, match="0.png: .*cannot be inverted"):
        load_scene(tmp_path, "colmap", **NEAR_FAR)


def test_a_nerfstudio_capture_is_undistorted_unless_the_distortion_is_ignored(tmp_path):
    root = nerfstudio_capture(tmp_path / "capture", {"k1": -0.09, "k2": 0.02, "p1": 0.001, "p2": -0.0015})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        undistorted = load_scene(root, "nerfstudio").views["0"]
    file_k = np.array([[60.0, 0.0, 35.5], [0.0, 61.0, 63.5], [0.0, 0.0, 1.0]])
    distortion = lens.perspective(k1=-0.09, k2=0.02, p1=0.001, p2=-0.0015)
    np.testing.assert_allclose(undistorted.camera.K, lens.pinhole_for(file_k, distortion, 72, 128))
    assert not np.allclose(undistorted.camera.K, file_k)
    with pytest.warns(UserWarning, match="lens distortion ignored") as record:
        ignored = load_scene(root, "nerfstudio", ignore_distortion=True).views["0"]
    assert len(record) == 1
    np.testing.assert_allclose(ignored.camera.K, file_k)
    np.testing.assert_allclose(ignored.image, ramp(72, 128), atol=0.5 / 255)


def test_nerfstudio_terms_opencv_has_not_are_refused_with_their_names(tmp_path):
    root = nerfstudio_capture(tmp_path / "opencv", {"k1": -0.09, "k4": 0.001})
    with pytest.raises(ValueError, match="k4 is not zero"):
        load_scene(root, "nerfstudio")
    root = nerfstudio_capture(tmp_path / "fisheye", {"camera_model": "OPENCV_FISHEYE", "k1": 0.05, "p2": 0.001})
    with pytest.raises(ValueError, match="p2 is not zero: OPENCV_FISHEYE has no tangential"):
        load_scene(root, "nerfstudio")


def test_a_nerfstudio_fisheye_capture_is_undistorted(tmp_path):
    root = nerfstudio_capture(tmp_path / "capture", {"camera_model": "OPENCV_FISHEYE", "k1": 0.05, "k2": -0.01})
    view = load_scene(root, "nerfstudio").views["0"]
    file_k = np.array([[60.0, 0.0, 35.5], [0.0, 61.0, 63.5], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(view.camera.K, lens.pinhole_for(file_k, lens.fisheye(0.05, -0.01), 72, 128))
    assert view.camera.K[0, 0] < 0.95 * 60.0, "a fisheye's pinhole image needs a wider view than its focal length says"
