"""manifest.json as typed objects (scnerf_export.export.manifest): every committed manifest reads
and writes back byte for byte; a manifest the server would refuse (a key missing, a guided policy
with a key it does not know) is refused here with the key named; keys the server ignores are kept."""

import json
import re
import shutil

import pytest

from scnerf_export.export.manifest import GuidedPolicy, Manifest, ManifestError

from conftest import REPO

COMMITTED = sorted(
    [*REPO.glob("bundles/*/manifest.json"), *REPO.glob("tests/fixtures/**/manifest.json")],
    key=str,
)
PARITY_BUNDLE = REPO / "tests" / "fixtures" / "parity" / "bundle"


def test_the_committed_manifests_are_found():
    assert REPO / "bundles" / "default" / "manifest.json" in COMMITTED
    assert PARITY_BUNDLE / "manifest.json" in COMMITTED


@pytest.mark.parametrize("path", COMMITTED, ids=lambda p: str(p.parent.relative_to(REPO)))
def test_a_committed_manifest_loads_and_writes_back_the_same_bytes(path, tmp_path):
    manifest = Manifest.load(path.parent)
    assert manifest.text() == path.read_text()
    manifest.save(tmp_path)
    assert (tmp_path / "manifest.json").read_bytes() == path.read_bytes()
    assert Manifest.load(tmp_path) == manifest


def test_the_typed_fields_hold_the_files_values():
    manifest = Manifest.load(PARITY_BUNDLE)
    data = json.loads((PARITY_BUNDLE / "manifest.json").read_text())
    assert manifest.model_id == data["model_id"] == manifest.expected_model_id()
    assert manifest.config.samples == data["config"]["samples"]
    assert manifest.config.encoder_channels == tuple(data["config"]["encoder_channels"])
    renderer = manifest.graphs["renderer"]
    assert renderer.file == "renderer.onnx" and renderer.sha256 == data["graphs"]["renderer"]["sha256"]
    assert renderer.input_names() == [t["name"] for t in data["graphs"]["renderer"]["inputs"]]
    assert renderer.inputs[0].shape == ["R", 3]
    assert manifest.guided == GuidedPolicy.from_json(data["guided"]) and manifest.guided.samples == (32, 16, 16)
    assert manifest.provenance.source_kind == "random-weights" and manifest.provenance.metrics is None
    assert manifest.precision == "fp32" and "precision" not in data


def write_changed(tmp_path, change) -> Manifest:
    """The parity bundle's manifest, changed by ``change`` (on its JSON), loaded from tmp_path."""
    data = json.loads((PARITY_BUNDLE / "manifest.json").read_text())
    change(data)
    (tmp_path / "manifest.json").write_text(json.dumps(data, indent=2) + "\n")
    return Manifest.load(tmp_path)


@pytest.mark.parametrize(
    "path",
    [
        ("provenance",),
        ("graphs",),
        ("format_version",),
        ("config", "samples"),
        ("graphs", "renderer", "sha256"),
        ("graphs", "encoder", "inputs", 0, "dtype"),
        ("guided", "support_threshold"),
        ("provenance", "exporter_version"),
    ],
    ids=lambda path: ".".join(map(str, path)),
)
def test_a_missing_required_key_is_refused_by_name(tmp_path, path):
    def drop(data):
        *parents, key = path
        for parent in parents:
            data = data[parent]
        del data[key]

    name = "".join(f"[{p}]" if isinstance(p, int) else f".{p}" for p in path).lstrip(".")
    with pytest.raises(ManifestError, match=rf"manifest\.json: missing {re.escape(name)}$"):
        write_changed(tmp_path, drop)


def test_optional_keys_may_be_absent(tmp_path):
    def plain(data):
        del data["guided"]
        del data["provenance"]["source_kind"]

    manifest = write_changed(tmp_path, plain)
    assert manifest.guided is None and manifest.provenance.source_kind is None
    assert "guided" not in manifest.to_json() and "source_kind" not in manifest.to_json()["provenance"]


def test_a_guided_policy_without_verification_reads_as_none_and_writes_back_alike(tmp_path):
    """Bundles written before verification keep rendering as they did: no pixel rendered again."""

    def plain(data):
        for key in GuidedPolicy.OPTIONAL:
            data["guided"].pop(key, None)

    manifest = write_changed(tmp_path, plain)
    assert manifest.guided.verify_tolerance is None and manifest.guided.verify_share is None
    assert manifest.guided.most_reruns(1000) == 0
    assert not set(GuidedPolicy.OPTIONAL) & set(manifest.to_json()["guided"])

    def half(data):
        data["guided"].pop("verify_share")

    with pytest.raises(ManifestError, match="come together"):
        write_changed(tmp_path, half)


def test_keys_the_server_ignores_are_kept(tmp_path):
    def annotate(data):
        data["comment"] = "made by hand"
        data["graphs"]["renderer"]["note"] = {"opset": 20}
        data["graphs"]["renderer"]["outputs"][0]["unit"] = "linear rgb"
        data["provenance"]["licence"] = None

    manifest = write_changed(tmp_path, annotate)
    assert manifest.extra == {"comment": "made by hand"}
    assert manifest.graphs["renderer"].extra == {"note": {"opset": 20}}
    assert manifest.provenance.extra == {"licence": None}
    assert manifest.text() == (tmp_path / "manifest.json").read_text()


def test_the_guided_policy_denies_unknown_keys_as_the_server_does(tmp_path):
    def extend(data):
        data["guided"]["levels"] = 3

    with pytest.raises(ManifestError, match=r"guided: unknown levels"):
        write_changed(tmp_path, extend)


def test_the_band_rule_reads_and_writes_back_and_is_absent_for_the_default(tmp_path):
    assert Manifest.load(REPO / "bundles" / "default").band == "when_dark"

    def always(data):
        data["band"] = {"fill": "always"}

    manifest = write_changed(tmp_path, always)
    assert manifest.band == "always" and manifest.to_json()["band"] == {"fill": "always"}
    assert manifest.text() == (tmp_path / "manifest.json").read_text()

    for band, message in (
        ({"fill": "sometimes"}, "band.fill: 'sometimes'"),
        ({"fill": "always", "x": 1}, "band: unknown key"),
    ):
        with pytest.raises(ManifestError, match=message):
            write_changed(tmp_path, lambda data, band=band: data.update(band=band))


def test_a_config_the_network_does_not_have_is_refused(tmp_path):
    def extend(data):
        data["config"]["dropout"] = 0.1

    with pytest.raises(ManifestError, match=r"config: unknown model config keys: \['dropout'\]"):
        write_changed(tmp_path, extend)


@pytest.mark.parametrize(
    "change,message",
    [
        (lambda d: d.update(format_version=2), "format_version is 2, this exporter reads format_version 1"),
        (lambda d: d.update(model_id=7), "model_id: expected str, got 7"),
        (lambda d: d["graphs"]["renderer"].update(inputs={}), "graphs.renderer.inputs: expected list, got {}"),
        (lambda d: d["graphs"]["encoder"]["inputs"][0].update(shape=[3, 3.5]), r"graphs.encoder.inputs[0].shape[1]"),
        (lambda d: d["guided"].update(step=6), "guided.step must be a power of two, got 6"),
        (lambda d: d["guided"].update(step=True), "guided.step: expected int, got true"),
        (lambda d: d.update(provenance=[]), "provenance: expected an object"),
    ],
)
def test_a_value_of_the_wrong_kind_is_refused_by_name(tmp_path, change, message):
    with pytest.raises(ManifestError, match=re.escape(message)):
        write_changed(tmp_path, change)


def test_a_reduced_precision_bundle_says_so_and_a_float32_one_does_not(tmp_path):
    shutil.copyfile(PARITY_BUNDLE / "manifest.json", tmp_path / "manifest.json")
    manifest = Manifest.load(tmp_path)
    manifest.precision = "int8"
    manifest.save(tmp_path)
    assert json.loads((tmp_path / "manifest.json").read_text())["precision"] == "int8"
    assert Manifest.load(tmp_path).precision == "int8"


def test_a_file_that_is_not_json_is_refused_with_its_path(tmp_path):
    (tmp_path / "manifest.json").write_text("{")
    with pytest.raises(ManifestError, match=re.escape(str(tmp_path / "manifest.json"))):
        Manifest.load(tmp_path)
