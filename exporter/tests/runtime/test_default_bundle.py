"""The committed default bundle on the committed example (a held-out procedural scene): its PSNR
stays above the floor in examples/procedural-object/regression.json (issue 4, regression test)."""

import json

import numpy as np
from PIL import Image

from scnerf_export.cameras import Camera
from scnerf_export.cameras import intrinsics_from_json as _k
from scnerf_export.evaluate import metrics
from scnerf_export.runtime.onnx_pipeline import OnnxBundle

from conftest import REPO

EXAMPLE = REPO / "examples" / "procedural-object"
BUNDLE = REPO / "bundles" / "default"


def load_rgb(path):
    return np.asarray(Image.open(path).convert("RGB"), dtype=np.float32) / 255.0


def camera(c: dict) -> Camera:
    return Camera.from_pose(_k(c), c["pose"]["matrix"], c["width"], c["height"], c["pose"]["kind"], c["pose"]["axes"])


def test_default_bundle_renders_the_example_above_its_floor():
    expected = json.loads((EXAMPLE / "regression.json").read_text())
    bundle = OnnxBundle(BUNDLE)
    assert bundle.manifest["model_id"] == expected["model_id"], "default bundle changed: re-measure the floor"
    assert bundle.manifest["provenance"]["source_kind"] == "scnerf-serve-training"
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
    assert metrics.psnr(result.rgb, load_rgb(EXAMPLE / "target_truth.png")) >= expected["psnr_floor"]
