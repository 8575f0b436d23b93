"""`scnerf-export reexport`: a 0.1 bundle's renderer read back from its graph and written again.

tests/fixtures/reexport-0.1 is the parity fixture bundle as scnerf-export 0.1 wrote it (random
weights, small config)."""

import hashlib
import shutil

import onnx
import pytest

from scnerf_export import __version__
from scnerf_export.cli import main
from scnerf_export.export.manifest import Manifest, model_id
from scnerf_export.export.reexport import ReexportError, reexport_bundle

from conftest import REPO

FIXTURE_BUNDLE = REPO / "tests" / "fixtures" / "reexport-0.1"
CURRENT_BUNDLE = REPO / "tests" / "fixtures" / "parity" / "bundle"


def sha256(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def reexported(tmp_path_factory):
    """The fixture bundle re-exported once for the module: its folder and manifest."""
    out = tmp_path_factory.mktemp("reexported") / "again"
    return out, reexport_bundle(FIXTURE_BUNDLE, out)


def test_reexport_reproduces_the_renderer_and_keeps_the_other_graphs(reexported):
    out, manifest = reexported
    source = Manifest.load(FIXTURE_BUNDLE)
    assert manifest.provenance.reexport["source_model_id"] == source.model_id
    assert manifest.provenance.reexport["renderer_max_abs_difference"] <= 1e-4
    files = {name: sha256(out / entry.file) for name, entry in manifest.graphs.items()}
    assert manifest.model_id == model_id(source.variant, files)
    assert manifest.graphs["renderer"].sha256 == sha256(out / "renderer.onnx")
    for name in ("encoder", "volume"):
        assert sha256(out / f"{name}.onnx") == sha256(FIXTURE_BUNDLE / f"{name}.onnx")
        assert manifest.graphs[name] == source.graphs[name]
    assert manifest.config == source.config
    assert Manifest.load(out) == manifest


def test_a_renderer_missing_a_weight_is_refused_in_one_line(tmp_path, capsys):
    broken = tmp_path / "broken"
    shutil.copytree(FIXTURE_BUNDLE, broken)
    proto = onnx.load(str(broken / "renderer.onnx"))
    for tensor in proto.graph.initializer:
        if tensor.name == "model.renderer.m1.feature_gate.weight":
            tensor.name = "renamed"
    for node in proto.graph.node:
        node.input[:] = ["renamed" if i == "model.renderer.m1.feature_gate.weight" else i for i in node.input]
    onnx.save(proto, str(broken / "renderer.onnx"))
    with pytest.raises(ReexportError, match="m1.feature_gate.weight"):
        reexport_bundle(broken, tmp_path / "out")
    assert main(["reexport", "--bundle", str(broken), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("scnerf-export reexport: error:") and "\n" not in err


def test_reexport_refuses_to_overwrite_its_source():
    with pytest.raises(ReexportError, match="--out must differ"):
        reexport_bundle(FIXTURE_BUNDLE, FIXTURE_BUNDLE)


def test_reexport_refuses_bundles_of_other_exporter_versions(tmp_path):
    with pytest.raises(ReexportError, match=f"written by scnerf-export {__version__}"):
        reexport_bundle(CURRENT_BUNDLE, tmp_path / "out")


def test_the_same_weights_export_to_the_same_bytes(reexported, tmp_path):
    """No addresses or stack traces in the graphs: the model id of a re-export is reproducible."""
    first_dir, first = reexported
    second = reexport_bundle(FIXTURE_BUNDLE, tmp_path / "b")
    assert first.model_id == second.model_id
    assert (first_dir / "renderer.onnx").read_bytes() == (tmp_path / "b" / "renderer.onnx").read_bytes()
