"""The committed default bundle: what it is (SC-NeRF derived from the public MVSNeRF weights, with
their licence) and what it renders. The committed example within 0.1 dB of
examples/tabletop/regression.json's full-sampling figure; regression floors 0.5 dB below the
measured figures, protocol as in docs/results.md (per target the 3 nearest source views, full-size
sources): lego r_28 at 200x200 >= 24.86 dB;
DTU scan37 view 32 (from 31, 33, 25) at 320x256 >= 22.11 dB on the object mask, through ONNX
Runtime and through the real server alike."""

import json

import numpy as np
import pytest
from PIL import Image

from scnerf_export.cameras import Camera, camera_json, target_rays
from scnerf_export.cameras import intrinsics_from_json as _k
from scnerf_export.data import datasets
from scnerf_export.evaluate import metrics
from scnerf_export.evaluate.eval import downscale_target, source_pool
from scnerf_export.export.manifest import Manifest
from scnerf_export.runtime.band import Sources, sightings, surface_points
from scnerf_export.runtime.onnx_pipeline import OnnxBundle
from scnerf_export.serving import ServerProcess, find_server_binary

from conftest import REPO, shared_dir

EXAMPLE = REPO / "examples" / "tabletop"
BUNDLE = REPO / "bundles" / "default"
PUBLIC_SHA256 = "84c2a397760d5e717c21faee9c4f8f8f8a1ba22b378b10971c44f4a0b932c124"
# Measured - 0.5 dB. lego r_28 at 200x200: 25.36 dB (`scnerf-export eval --target-scale 0.25`,
# bundles/default/eval/lego.json, docs/client.md); scan37 view 32 at 320x256, object-masked:
# 22.61 dB (docs/results.md, "Through the server, targets at half size").
LEGO_FLOOR_DB, SCAN37_MASKED_FLOOR_DB = 24.86, 22.11
SERVER_AGREEMENT_DB = 0.1
GUIDED_LOSS_DB = 0.3
SPECKLED_SHARE = 0.001


def load_rgb(path):
    return np.asarray(Image.open(path).convert("RGB"), dtype=np.float32) / 255.0


def camera(c: dict) -> Camera:
    return Camera.from_pose(_k(c), c["pose"]["matrix"], c["width"], c["height"], c["pose"]["kind"], c["pose"]["axes"])


def test_default_bundle_is_scnerf_derived_from_the_public_weights_with_their_licence():
    manifest = Manifest.load(BUNDLE)
    assert manifest.variant == "scnerf"
    assert (manifest.config.depth_planes, manifest.config.samples, manifest.config.width) == (128, 128, 128)
    base = manifest.provenance.derived_from
    assert base["source_sha256"] == PUBLIC_SHA256 and base["licence"] == "MIT"
    assert "Permission is hereby granted" in (BUNDLE / base["licence_file"]).read_text()
    training = manifest.provenance.training
    assert {"data", "steps", "seed"} <= set(training)
    assert sum(p.stat().st_size for p in BUNDLE.rglob("*") if p.is_file()) < 10 * 2**20


@pytest.mark.slow
def test_default_bundle_renders_the_example_as_measured():
    expected = json.loads((EXAMPLE / "regression.json").read_text())
    bundle = OnnxBundle(BUNDLE)
    assert bundle.model_id == expected["model_id"], "default bundle changed: re-measure the floor"
    request = json.loads((EXAMPLE / "request.json").read_text())
    images = np.stack([load_rgb(EXAMPLE / f"source_{i}.png") for i in range(3)])
    result = bundle.render_view(
        images,
        [camera(s["camera"]) for s in request["sources"]],
        camera(request["target"]),
        request["near"],
        request["far"],
        tuple(request["background"]),
    )
    score = metrics.psnr(result.rgb, load_rgb(EXAMPLE / "target_truth.png"))
    assert abs(score - expected["psnr_full"]) <= expected["tolerance_db"], f"{score:.3f} dB"


class RealView:
    """A target of a real scene, its sources and how it is scored."""

    def __init__(
        self, folder: str, fmt: str, target: str, sources: list[str] | None, scale: float, image_scale: float = 1.0
    ):
        path = shared_dir() / "data" / folder
        if not path.is_dir():
            pytest.skip(f"{path} not found (../shared is absent on this machine)")
        self.scene = datasets.load_scene(path, fmt, scale=image_scale)
        pool = source_pool(self.scene, [target])
        self.source_names = sources or datasets.nearest_sources(self.scene, target, pool)
        self.sources = datasets.get_views(self.scene, self.source_names)
        self.target = downscale_target(self.scene.views[target], scale)
        self.image_files = [self.image_file(path, fmt, name) for name in self.source_names]

    @staticmethod
    def image_file(path, fmt, name):
        if fmt == "dtu":
            return next((path / "Rectified").glob(f"*/rect_{int(name) + 1:03d}_3_r5000.png"))
        if fmt == "llff":
            return path / "images_8" / f"{name}.png"
        return path / "train" / f"{name}.png"

    def render_onnx(self) -> np.ndarray:
        s = self.scene
        return (
            OnnxBundle(BUNDLE)
            .render_view(
                np.stack([v.image for v in self.sources]),
                [v.camera for v in self.sources],
                self.target.camera,
                s.near,
                s.far,
                s.background,
            )
            .rgb
        )

    def render_served(self, server: ServerProcess, sampling: str, target: Camera | None = None) -> np.ndarray:
        return self.served_view(server, sampling, target, outputs=["rgb"]).rgb

    def served_view(self, server: ServerProcess, sampling: str, target: Camera | None = None, outputs=("rgb",)):
        s = self.scene
        return server.client.render(
            [f.read_bytes() for f in self.image_files],
            [camera_json(v.camera) for v in self.sources],
            camera_json(target or self.target.camera),
            s.near,
            s.far,
            s.background,
            outputs=list(outputs),
            sampling=sampling,
        )

    def band(self, depth: np.ndarray) -> np.ndarray:
        """The target's pixels whose surface (at ``depth``) some of the sources do not see (runtime/band.py)."""
        sources = Sources.of_views(np.stack([v.image for v in self.sources]), [v.camera for v in self.sources])
        views, *_ = sightings(surface_points(depth.reshape(-1), *target_rays(self.target.camera)), sources)
        return ((views > 0) & (views < len(self.sources))).reshape(depth.shape)

    def psnr(self, rgb: np.ndarray) -> float:
        if self.target.mask is not None:
            return metrics.dtu_masked_metrics(rgb, self.target.image, self.target.mask)["psnr"]
        return metrics.psnr(rgb, self.target.image)


@pytest.fixture(scope="module")
def lego_r28():
    return RealView("nerf_synthetic_lego", "blender", "r_28", None, 0.25)


@pytest.fixture(scope="module")
def scan37_view32():
    return RealView("dtu_scan37", "dtu", "32", None, 0.5)


@pytest.fixture(scope="module")
def scan37_onnx_psnr(scan37_view32):
    return scan37_view32.psnr(scan37_view32.render_onnx())


@pytest.mark.slow
def test_lego_r28_from_its_nearest_views(lego_r28):
    assert lego_r28.psnr(lego_r28.render_onnx()) >= LEGO_FLOOR_DB


@pytest.mark.slow
def test_scan37_view32_on_its_object(scan37_onnx_psnr):
    assert scan37_onnx_psnr >= SCAN37_MASKED_FLOOR_DB


@pytest.mark.slow
def test_the_server_renders_scan37_view32_as_onnx_runtime_does_guided_within_its_bound(scan37_view32, scan37_onnx_psnr):
    binary = find_server_binary()
    assert binary is not None, "no scnerf-server binary under target/: build it first (scripts/test.sh does)"
    with ServerProcess(binary, BUNDLE) as server:
        served = scan37_view32.psnr(scan37_view32.render_served(server, "full"))
        guided = scan37_view32.psnr(scan37_view32.render_served(server, "guided"))
    assert served >= SCAN37_MASKED_FLOOR_DB
    assert abs(served - scan37_onnx_psnr) <= SERVER_AGREEMENT_DB
    # The default sampling's bound: within 0.3 dB of every sample on every ray.
    assert guided >= served - GUIDED_LOSS_DB


@pytest.fixture(scope="module")
def horns_view0():
    """LLFF horns' first held-out view (LLFF's every 8th) at 252x189 from its 3 nearest others."""
    return RealView("llff_horns", "llff", "DJI_20200223_163016_842", None, 0.5, image_scale=1 / 8)


@pytest.fixture(scope="module")
def horns_view0_small():
    """The same view at 168x126: guided sampling's policy at a size the fast tier can afford."""
    return RealView("llff_horns", "llff", "DJI_20200223_163016_842", None, 1 / 3, image_scale=1 / 8)


@pytest.fixture(scope="module")
def horns_server():
    binary = find_server_binary()
    assert binary is not None, "no scnerf-server binary under target/: build it first (scripts/test.sh does)"
    with ServerProcess(binary, BUNDLE, extra=("--request-timeout-secs", "3600")) as server:
        yield server


def full_and_guided(view: RealView, server: ServerProcess):
    """``view`` served at full sampling (colour and depth) and guided (colour)."""
    return view.served_view(server, "full", outputs=("rgb", "depth")), view.render_served(server, "guided")


@pytest.fixture(scope="module")
def horns_renders(horns_view0, horns_server):
    return full_and_guided(horns_view0, horns_server)


def speckled_share(full: np.ndarray, guided: np.ndarray) -> float:
    """Pixels where guided and full sampling differ by more than 0.25 in a channel."""
    return float((np.abs(guided - full).max(axis=2) > 0.25).mean())


def test_guided_leaves_no_speckles_on_a_real_capture_at_a_third_of_its_size(horns_view0_small, horns_server):
    full, guided = full_and_guided(horns_view0_small, horns_server)
    speckled = speckled_share(full.rgb, guided)
    assert speckled <= SPECKLED_SHARE, f"{speckled:.3%} of the pixels differ by more than 0.25"


@pytest.mark.slow
def test_guided_leaves_no_speckles_on_a_real_capture(horns_renders):
    """At most 0.1 % of the pixels: 0.54 % of the view before pixels that disagree with their
    neighbours were rendered again, 0.22 % after, 0.057 % with edges at 32 samples and a re-render
    tolerance of 0.1 (docs/results.md)."""
    full, guided = horns_renders
    speckled = speckled_share(full.rgb, guided)
    assert speckled <= SPECKLED_SHARE, f"{speckled:.3%} of the pixels differ by more than 0.25"


@pytest.mark.slow
def test_guided_fills_no_block_of_a_smooth_region_with_one_colour(horns_view0, horns_server):
    """The pillar and the wall behind it at four times the size (1008x756; a 160x96 window):
    no 8x8 block of the guided view is one colour where the full render's is not."""
    window = crop(horns_view0.target.camera.scaled(4.0), top=100, left=400, width=160, height=96)
    full, guided = (horns_view0.render_served(horns_server, mode, window) for mode in ("full", "guided"))

    def spread(image):  # per 8x8 block, the largest range of a channel
        blocks = image[: 96 // 8 * 8, : 160 // 8 * 8].reshape(12, 8, 20, 8, 3)
        return (blocks.max(axis=(1, 3)) - blocks.min(axis=(1, 3))).max(axis=-1)

    one_colour = (spread(guided) < 1 / 255) & (spread(full) > 4 / 255)
    assert not one_colour.any(), f"{one_colour.sum()} blocks of one colour"


@pytest.mark.slow
def test_pixels_a_source_misses_are_as_bright_as_the_photo(horns_view0, horns_renders):
    """Where the surface lies outside one of the sources' images (the band along the view's edges),
    the served colour is nearly as bright as the photo's: 0.039 darker on average, where the network
    alone renders it 0.185 darker (the pixels every source sees: 0.007; docs/results.md, "The band")."""
    view, _ = horns_renders
    band = horns_view0.band(view.depth)
    assert band.mean() > 0.05, f"{band.mean():.1%} of the view in the band: no band to test"
    darker = (horns_view0.target.image[band] - view.rgb[band]).mean()
    assert abs(darker) < 0.08, f"the band's pixels are {darker:.3f} darker than the photo's"


def crop(camera: Camera, top: int, left: int, width: int, height: int) -> Camera:
    """The window of ``camera``'s image at (top, left), as a camera of its own."""
    K = camera.K.copy()
    K[0, 2] -= left
    K[1, 2] -= top
    return Camera(K, camera.w2c, width, height)
