"""scnerf_client against a real server (conftest.py): renders as arrays, scenes and their
re-upload, captures as distributed (what is sent of them planned by the server), typed errors."""

from __future__ import annotations

import io
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from scnerf_client import (
    Camera,
    Client,
    InvalidRequest,
    ModelMismatch,
    ModelNotFound,
    SceneNotFound,
    Unauthorized,
    captures,
)
from scnerf_client.client import Client as _Client

#: Forward-facing views on a small grid, looking down the world's -z; the scene between 2 and 6.
CENTRES = [(0.0, 0.0), (0.3, 0.1), (-0.3, 0.1), (0.1, -0.3), (-0.1, 0.3)]


def camera(x: float, y: float, width: int = 32, height: int = 24) -> Camera:
    pose = np.array([[1, 0, 0, x], [0, -1, 0, y], [0, 0, -1, 0], [0, 0, 0, 1]], float)
    return Camera(width, height, width, width, width / 2 - 0.5, height / 2 - 0.5, pose, "camera_to_world", "opencv")


def photo(view: int, width: int, height: int) -> np.ndarray:
    y, x = np.mgrid[0:height, 0:width]
    return np.stack([x * 255 // width, y * 255 // height, np.full_like(x, 40 * view % 256)], -1).astype(np.uint8)


def llff_as_distributed(folder, full=(256, 192), factors=(4, 8)) -> None:
    """LLFF's layout: poses_bounds.npy (hwf of the full-size images), images/ JPEGs, images_N PNGs."""
    w, h = full
    rows = []
    for i, (x, y) in enumerate(CENTRES):
        # [down, right, back | centre | hwf] per row x, y, z; then near, far
        rows.append([0, 1, 0, x, h, -1, 0, 0, y, w, 0, 0, 1, 0, w, 2.0, 6.0])
        (folder / "images").mkdir(exist_ok=True)
        Image.fromarray(photo(i, w, h)).save(folder / "images" / f"IMG_{i:04}.jpg")
        for n in factors:
            (folder / f"images_{n}").mkdir(exist_ok=True)
            Image.fromarray(photo(i, w // n, h // n)).save(folder / f"images_{n}" / f"IMG_{i:04}.png")
    np.save(folder / "poses_bounds.npy", np.array(rows, np.float64))


@pytest.fixture
def client(server) -> Client:
    return Client(server.url)


def test_model_and_limits(client):
    assert client.model()["model_id"]
    limits = client.limits()
    assert limits.max_source_pixels == 3072 and limits.max_scene_views >= 3 and limits.max_body_bytes > 0


def test_render_returns_arrays_and_a_scene_renders_the_same(client):
    images = [photo(i, 32, 24) for i in range(3)]
    cameras = [camera(x, y) for x, y in CENTRES[:3]]
    target = camera(0.05, 0.05, 16, 12)
    one_shot = client.render(images, cameras, target, near=2.0, far=6.0)
    assert one_shot.rgb.shape == (12, 16, 3) and one_shot.rgb.dtype == np.float32
    assert 0.0 <= one_shot.rgb.min() and one_shot.rgb.max() <= 1.0
    assert one_shot.depth.shape == (12, 16) and one_shot.opacity.shape == (12, 16)
    assert one_shot.timings["total"] > 0 and one_shot.model_id
    scene = client.upload_scene(images, cameras, near=2.0, far=6.0)
    assert scene.id.startswith("py-") and len(scene.cameras) == 3
    cached = client.render_scene(scene, target)
    np.testing.assert_array_equal(cached.rgb, one_shot.rgb)
    np.testing.assert_array_equal(cached.depth, one_shot.depth)
    only_rgb = client.render_scene(scene, target, outputs=["rgb"])
    assert only_rgb.depth is None and only_rgb.opacity is None


def test_a_scene_that_is_gone_is_uploaded_again_once(client):
    images = [photo(i, 32, 24) for i in range(3)]
    scene = client.upload_scene(images, [camera(x, y) for x, y in CENTRES[:3]], near=2.0, far=6.0, scene_id="nb-1")
    target = camera(0.0, 0.0, 8, 6)
    first = client.render_scene(scene, target)
    client.delete_scene(scene)
    again = client.render_scene(scene, target)
    assert scene.id == "nb-1"
    np.testing.assert_array_equal(again.rgb, first.rgb)
    client.delete_scene(scene)
    with pytest.raises(SceneNotFound) as gone:
        client.render_scene("nb-1", target)  # an id alone cannot be uploaded again
    assert (gone.value.status, gone.value.field, gone.value.hint) == (404, "scene_id", "reupload")


def test_errors_carry_code_field_and_hint(client, token_server):
    images = [photo(i, 32, 24) for i in range(3)]
    cameras = [camera(x, y) for x, y in CENTRES[:3]]
    with pytest.raises(InvalidRequest) as bad:
        client.render(images, cameras, camera(0, 0, 8, 6), near=6.0, far=2.0)
    assert bad.value.status == 422 and bad.value.code == "invalid_request" and bad.value.field in ("near", "far")
    with pytest.raises(Unauthorized) as refused:
        Client(token_server.url).model()
    assert refused.value.status == 401 and refused.value.field == "authorization"
    assert Client(token_server.url, token="secret-token").model()["model_id"]


def test_sampling_is_sent_only_when_given_and_said_back(client):
    target = camera(0, 0)
    assert "sampling" not in _Client._target_document(target, ["rgb"], None)
    assert _Client._target_document(target, ["rgb"], "guided")["sampling"] == "guided"
    images = [photo(i, 32, 24) for i in range(3)]
    cameras = [camera(x, y) for x, y in CENTRES[:3]]
    view = camera(0.05, 0.05, 16, 12)
    full = client.render(images, cameras, view, near=2.0, far=6.0, sampling="full")
    guided = client.render(images, cameras, view, near=2.0, far=6.0, sampling="guided")
    samples = client.model()["config"]["samples"]
    assert (full.sampling, full.samples_per_ray) == ("full", samples)
    assert guided.sampling == "guided" and 0 < guided.samples_per_ray < samples
    with pytest.raises(InvalidRequest) as bad:
        client.render(images, cameras, view, near=2.0, far=6.0, sampling="fast")
    assert (bad.value.status, bad.value.field) == (422, "sampling")


def test_the_model_is_sent_only_when_named_and_each_render_says_its_model(models_server, models_dir):
    bundle = Path(__file__).resolve().parents[2] / "tests/fixtures/parity/bundle"
    client = Client(models_server.url)
    assert "model" not in _Client._scene_document([], 2.0, 6.0, None)
    assert _Client._scene_document([], 2.0, 6.0, None, "second")["model"] == "second"
    assert [(m["name"], m["default"]) for m in client.models()] == [("bundle", True)]
    shutil.copytree(bundle, models_dir / "second")
    reloaded = client.reload_models()
    assert [m["name"] for m in reloaded["loaded"]] == ["second"] and reloaded["skipped"] == []
    assert [m["name"] for m in client.models()] == ["bundle", "second"]

    images = [photo(i, 32, 24) for i in range(3)]
    cameras = [camera(x, y) for x, y in CENTRES[:3]]
    target = camera(0.05, 0.05, 16, 12)
    assert client.render(images, cameras, target, near=2.0, far=6.0, model="second").model == "second"
    assert client.render(images, cameras, target, near=2.0, far=6.0).model == "bundle"
    scene = client.upload_scene(images, cameras, near=2.0, far=6.0, model="second")
    assert scene.model == "second"
    assert client.render_scene(scene, target).model == "second"
    with pytest.raises(ModelMismatch) as mismatch:
        client.render_scene(scene, target, model="bundle")
    assert (mismatch.value.status, mismatch.value.field) == (409, "model")
    with pytest.raises(ModelNotFound) as unknown:
        client.render(images, cameras, target, near=2.0, far=6.0, model="nerf")
    assert (unknown.value.status, unknown.value.field) == (404, "model") and "nerf" in unknown.value.message


def test_capture_as_distributed_sends_the_largest_set_that_fits(client, tmp_path):
    llff_as_distributed(tmp_path)
    scene = client.upload_capture(tmp_path)
    assert (scene.format, scene.image_set, len(scene.cameras)) == ("llff", "images_4", 5)
    assert scene.cameras[0]["width"] == 64 and scene.names[0] == "images_4/IMG_0000.png"
    assert not any("not read" in w for w in scene.warnings), "only the chosen set was sent"
    view = client.render_scene(scene, scene.cameras[0])
    assert view.rgb.shape == (48, 64, 3) and len(view.sources) == 3
    smaller = client.upload_capture(tmp_path, downscale=8)
    assert (smaller.image_set, smaller.cameras[0]["width"]) == ("images_8", 32)
    # focal lengths follow the set (LLFF's hwf describes the full-size images)
    assert smaller.cameras[0]["intrinsics"]["fx"] == pytest.approx(scene.cameras[0]["intrinsics"]["fx"] / 2)


def test_capture_without_a_set_that_fits_is_resized_here(client, tmp_path):
    llff_as_distributed(tmp_path, full=(128, 96), factors=())
    scene = client.upload_capture(tmp_path)
    assert scene.image_set == "images" and (scene.cameras[0]["width"], scene.cameras[0]["height"]) == (64, 48)
    assert scene.notes == [
        "5 images of 128x96 exceed the server's limit of 3072 pixels per source view: resizing them to 64x48"
    ]
    assert not scene.warnings, "resized here as planned: nothing left for the server to resize"
    (tmp_path / "poses_bounds.npy").unlink()  # images without cameras: refused, saying why
    with pytest.raises(InvalidRequest) as refused:
        client.upload_capture(tmp_path)
    assert refused.value.status == 422 and "cannot tell the dataset format" in refused.value.message


def test_the_server_plans_what_is_sent_of_a_capture(client, tmp_path):
    """Any case of png/jpg/jpeg is an image, hidden files never go, images_1 is no set: the
    server's rules (POST /v1/captures/plan), asked with the listing and one size per folder."""
    llff_as_distributed(tmp_path)
    for i in range(len(CENTRES)):  # extensions as phones and tools write them
        (tmp_path / "images" / f"IMG_{i:04}.jpg").rename(tmp_path / "images" / f"IMG_{i:04}.JPG")
        (tmp_path / "images_4" / f"IMG_{i:04}.png").rename(tmp_path / "images_4" / f"IMG_{i:04}.Png")
    (tmp_path / ".DS_Store").write_bytes(b"\0")
    (tmp_path / "images_4" / "._IMG_0000.Png").write_bytes(b"\0")
    (tmp_path / "notes.md").write_text("taken at noon")
    (tmp_path / "images_1").mkdir()
    Image.fromarray(photo(0, 8, 6)).save(tmp_path / "images_1" / "a.png")
    asked = []

    def ask(listing):
        asked.append(dict(listing))
        return client._plan_capture(listing)

    planned = captures.plan(tmp_path, ask)
    assert [sorted(s["path"] for s in a.get("sizes", [])) for a in asked] == [
        [],
        ["images/IMG_0000.JPG", "images_1/a.png", "images_4/IMG_0000.Png", "images_8/IMG_0000.png"],
    ], "one header read per folder of images"
    assert planned["image_set"] == "images_4" and [s["folder"] for s in planned["image_sets"]] == [
        "images",
        "images_4",
        "images_8",
    ]
    sent = [f["path"] for f in planned["send"]]
    assert sent == ["images_1/a.png", *(f"images_4/IMG_{i:04}.Png" for i in range(5)), "poses_bounds.npy"]
    reasons = {f["path"]: f["reason"] for f in planned["left_out"]}
    assert reasons[".DS_Store"] == reasons["images_4/._IMG_0000.Png"] == "hidden"
    assert reasons["notes.md"] == "not_capture_file" and reasons["images/IMG_0000.JPG"] == "other_image_set"
    scene = client.upload_capture(tmp_path)
    assert (scene.image_set, scene.cameras[0]["width"], scene.names[0]) == ("images_4", 64, "images_4/IMG_0000.Png")
    assert scene.notes[0].startswith("image set: images_4 (64x48) of images (256x192)"), scene.notes
    assert scene.notes[1].startswith("not sent: notes.md, neither images"), scene.notes
    with pytest.raises(InvalidRequest) as refused:
        client.upload_capture(tmp_path, downscale=2)
    assert (refused.value.status, refused.value.field) == (422, "downscale")
    assert "no images_2 folder" in refused.value.message


def test_images_are_resized_upright_to_the_size_the_server_says():
    """A phone JPEG stored 96x54 and tagged "rotate 90" is 54x96 as displayed, as the server reads
    it: its size is read so, and it is resized upright; an image of another size stays as it is."""
    exif = Image.Exif()
    exif[0x0112] = 6
    stored = io.BytesIO()
    Image.fromarray(photo(0, 96, 54)).save(stored, format="JPEG", exif=exif)
    data = stored.getvalue()
    resize = {"from": {"width": 54, "height": 96}, "to": {"width": 41, "height": 73}}
    with Image.open(io.BytesIO(captures.resized(data, resize))) as out:
        assert (out.format, out.size) == ("JPEG", (41, 73))
    other = {"from": {"width": 96, "height": 54}, "to": {"width": 73, "height": 41}}
    assert captures.resized(data, other) == data


def test_displayed_sizes_apply_the_exif_orientation(tmp_path):
    exif = Image.Exif()
    exif[0x0112] = 6
    Image.fromarray(photo(0, 96, 54)).save(tmp_path / "turned.jpg", exif=exif)
    Image.fromarray(photo(0, 96, 54)).save(tmp_path / "plain.png")
    assert captures.displayed_size(tmp_path / "turned.jpg") == (54, 96)
    assert captures.displayed_size(tmp_path / "plain.png") == (96, 54)


def phone_capture(folder, size=(54, 96), count=6) -> None:
    """instant-ngp's layout as a phone capture leaves it: the camera with lens distortion at the top
    level of transforms.json, no depth range, portrait JPEGs; views on a ring around the origin."""
    (folder / "images").mkdir()
    w, h = size
    frames = []
    for i in range(count):
        a = 0.3 * i
        eye = np.array([5 * np.cos(a), 5 * np.sin(a), 1.0])
        back = eye / np.linalg.norm(eye)  # OpenGL: z points backwards, away from the origin
        right = np.cross([0.0, 0.0, 1.0], back)
        right /= np.linalg.norm(right)
        c2w = np.eye(4)
        c2w[:3, :3] = np.stack([right, np.cross(back, right), back], 1)
        c2w[:3, 3] = eye
        Image.fromarray(photo(i, w, h)).save(folder / "images" / f"{i:04}.jpg")
        frames.append({"file_path": f"images/{i:04}.jpg", "transform_matrix": c2w.tolist()})
    transforms = {"fl_x": 0.9 * h, "fl_y": 0.9 * h, "cx": w / 2, "cy": h / 2, "w": w, "h": h, "k1": -0.06,
                  "k2": 0.01, "p1": 0.0005, "p2": -0.0003, "aabb_scale": 16, "frames": frames}  # fmt: skip
    (folder / "transforms.json").write_text(json.dumps(transforms))


def test_a_phone_capture_is_undistorted_and_fitted_by_the_server(client, tmp_path):
    phone_capture(tmp_path)
    scene = client.upload_capture(tmp_path)
    # the images (5184 pixels) are over the limit (3072): resized here, undistorted by the server
    assert (scene.cameras[0]["width"], scene.cameras[0]["height"]) == (41, 73)
    assert "6 images of 54x96 exceed the server's limit of 3072 pixels per source view" in scene.notes[0]
    fx = scene.cameras[0]["intrinsics"]["fx"]
    assert fx < 0.9 * 96 * 41 / 54, "barrel distortion squeezed a wider view into the photo than its focal length says"
    assert 0 < scene.near < scene.far
    view = client.render_scene(scene, scene.cameras[0])
    assert view.rgb.shape == (73, 41, 3)


def test_reprs_are_one_line(client, tmp_path):
    llff_as_distributed(tmp_path)
    scene = client.upload_capture(tmp_path)
    text = repr(scene)
    assert "\n" not in text and len(text) < 200, text
    assert text == f"Scene({scene.id!r}, llff, images_4, 5 views at 64x48, near 2 far 6)"
    view = client.render_scene(scene, scene.cameras[0])
    assert repr(view).startswith(f"Rendering(64x48 rgb+depth+opacity, sources {view.sources}")
    assert repr(camera(0.5, 0.0)) == "Camera(32x24, f 32,32, c 15.5,11.5, centre (0.5, 0, 0), camera_to_world opencv)"
