"""`scnerf-export split-volume`: a bundle's volume graphs written again for another way of building
the volume: slab by slab of depth planes (cost_slab.onnx + volume_net.onnx) or from the server's
plane sweep (cost_conv.onnx + volume_net.onnx).

tests/fixtures/parity-slabs and parity-sweep hold the two graphs and the manifest that split-volume
wrote for the parity fixture bundle from its model (`scnerf-export fixtures`; the other graphs are
that bundle's own). tests/fixtures/g2-readback holds a bundle and its slab graphs in the form
earlier exporters wrote (norms as chains of operators), which split-volume reads G2 back from."""

import hashlib
import shutil
from types import SimpleNamespace

import numpy as np
import pytest

from scnerf_export.cli import main
from scnerf_export.config import small_config
from scnerf_export.export import bundle as bundle_module
from scnerf_export.export.bundle import GUIDED_GRAPHS
from scnerf_export.export.manifest import Manifest
from scnerf_export.export.split_volume import SplitVolumeError, check_inputs, split_volume_bundle, volumes_agree
from scnerf_export.model.checkpoint import save_checkpoint
from scnerf_export.rigs import random_model
from scnerf_export.runtime.onnx_pipeline import OnnxBundle
from scnerf_export.runtime.volume_slabs import SLAB_BYTES_PER_CELL, build_volume, planes_per_slab

from conftest import REPO

FIXTURES = REPO / "tests" / "fixtures"
WHOLE = FIXTURES / "parity" / "bundle"
SPLIT = {"slabs": (FIXTURES / "parity-slabs", "cost_slab"), "sweep": (FIXTURES / "parity-sweep", "cost_conv")}
# G2 in the form split-volume reads back: a bundle with one volume graph, and its slab graphs.
READBACK = FIXTURES / "g2-readback" / "bundle"
READBACK_SLABS = FIXTURES / "g2-readback" / "slabs"


def sha256(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


def assembled(tmp_path, split, whole):
    """The bundle of the split graphs and manifest in ``split``, with the other graphs its manifest
    names taken from the bundle ``whole``."""
    out = tmp_path / split.name
    out.mkdir()
    shutil.copyfile(split / "manifest.json", out / "manifest.json")
    for entry in Manifest.load(split).graphs.values():
        shutil.copyfile(split / entry.file if (split / entry.file).is_file() else whole / entry.file, out / entry.file)
    return out


def split_bundle(tmp_path, build):
    """The committed split graphs of ``build`` with the parity bundle's other graphs."""
    return assembled(tmp_path, SPLIT[build][0], WHOLE)


def check_inputs_of_the_whole_bundle():
    cfg = Manifest.load(WHOLE).config
    return cfg, check_inputs(WHOLE / "encoder.onnx", cfg)


def test_the_committed_slab_graphs_give_the_volume_graphs_volume_at_any_slab_size():
    cfg, inputs = check_inputs_of_the_whole_bundle()
    sizes = (1, 3, 7, cfg.depth_planes)
    assert volumes_agree(WHOLE, Manifest.load(WHOLE), SPLIT["slabs"][0], "slabs", inputs, sizes) <= 1e-4


def test_the_committed_sweep_graphs_give_the_volume_graphs_volume_at_any_slab_size():
    cfg, inputs = check_inputs_of_the_whole_bundle()
    sizes = (1, 3, 7, cfg.depth_planes)
    assert volumes_agree(WHOLE, Manifest.load(WHOLE), SPLIT["sweep"][0], "sweep", inputs, sizes) <= 1e-4


@pytest.mark.parametrize("build", ["slabs", "sweep"])
def test_a_split_bundle_renders_what_the_whole_one_renders(tmp_path, build):
    whole, split = OnnxBundle(WHOLE), OnnxBundle(split_bundle(tmp_path, build))
    assert set(split.sessions) == {"encoder", SPLIT[build][1], "volume_net", "renderer", *GUIDED_GRAPHS}
    cfg, inputs = check_inputs_of_the_whole_bundle()
    _, _, h, w = inputs["features"].shape
    cells = (h + 2 * cfg.pad) * (w + 2 * cfg.pad)
    want = whole.sessions["volume"].run(None, inputs)[0]
    volumes = []
    for planes in (1, 4, cfg.depth_planes):
        budget = (planes + 2) * SLAB_BYTES_PER_CELL[build] * cells
        assert planes_per_slab(build, cfg.depth_planes, cells, budget) == planes
        volumes.append(build_volume(split.sessions, inputs, cfg, budget))
        assert np.abs(volumes[-1] - want).max() <= 1e-4
    # How many planes a slab run takes does not change the volume.
    assert all(np.array_equal(v, volumes[0]) for v in volumes[1:])


@pytest.mark.parametrize("build", ["slabs", "sweep"])
def test_the_manifest_keeps_the_config_and_names_the_split(build):
    fixture, slab_graph = SPLIT[build]
    whole, split = Manifest.load(WHOLE), Manifest.load(fixture)
    assert split.config == whole.config
    assert split.model_id == split.expected_model_id() != whole.model_id  # other graphs, another model
    assert list(split.graphs) == ["encoder", slab_graph, "volume_net", "renderer", *GUIDED_GRAPHS]
    for name in ("encoder", "renderer", *GUIDED_GRAPHS):
        assert split.graphs[name] == whole.graphs[name]
    for name in (slab_graph, "volume_net"):
        assert split.graphs[name].sha256 == sha256(fixture / f"{name}.onnx")
    assert split.provenance.volume_split["volume_max_abs_difference"] <= 1e-4


@pytest.mark.slow
def test_split_volume_writes_graphs_that_agree_with_the_volume_graph(tmp_path):
    out = tmp_path / "out"
    manifest = split_volume_bundle(READBACK, out)
    assert list(manifest.graphs) == ["encoder", "cost_conv", "volume_net", "renderer", *GUIDED_GRAPHS]
    assert manifest.provenance.volume_split["volume_max_abs_difference"] <= 1e-4
    assert not (out / "volume.onnx").exists()
    for name in ("encoder.onnx", "renderer.onnx"):
        assert (out / name).read_bytes() == (READBACK / name).read_bytes()
    assert Manifest.load(out) == manifest
    with pytest.raises(SplitVolumeError, match="already build the volume as 'sweep'"):
        split_volume_bundle(out, tmp_path / "again")
    # Graphs in the form the exporter writes now are not read back.
    with pytest.raises(SplitVolumeError, match="export the bundle from its checkpoint"):
        split_volume_bundle(out, tmp_path / "back", "slabs")


@pytest.mark.slow
def test_split_volume_reads_g2_back_from_a_slab_bundle(tmp_path):
    """G2's first convolution in cost_slab.onnx, its norm in volume_net.onnx (as bundles/default had
    them)."""
    slabs = assembled(tmp_path, READBACK_SLABS, READBACK)
    swept = split_volume_bundle(slabs, tmp_path / "slabs-sweep")
    assert list(swept.graphs) == ["encoder", "cost_conv", "volume_net", "renderer"]
    assert swept.provenance.volume_split["volume_max_abs_difference"] <= 1e-4
    assert swept.model_id == swept.expected_model_id() != Manifest.load(READBACK).model_id


def test_split_volume_takes_g2_from_a_model_of_the_bundles_config_only(tmp_path):
    with pytest.raises(SplitVolumeError, match="the model's config is not the bundle's"):
        split_volume_bundle(WHOLE, tmp_path / "out", model=random_model(small_config("mvsnerf"), seed=0))
    assert not (tmp_path / "out").exists()


def test_split_volume_refuses_to_overwrite_its_source_in_one_line(capsys):
    with pytest.raises(SplitVolumeError, match="--out must differ"):
        split_volume_bundle(WHOLE, WHOLE)
    slabs = SPLIT["slabs"][0]
    assert main(["split-volume", "--bundle", str(slabs), "--out", str(slabs)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("scnerf-export split-volume: error:") and "\n" not in err


def test_export_builds_the_volume_by_the_sweep_unless_asked_for_another_build(tmp_path, monkeypatch):
    """The command's choice of build; what each build writes is the slow test below's."""
    save_checkpoint(tmp_path / "c.pt", random_model(small_config("scnerf"), seed=0), {})
    asked = []

    def record(model, out, provenance, volume):
        asked.append(volume)
        return SimpleNamespace(model_id="recorded")

    monkeypatch.setattr(bundle_module, "export_bundle", record)
    checkpoint = str(tmp_path / "c.pt")
    assert main(["export", "--checkpoint", checkpoint, "--out", str(tmp_path / "sweep")]) == 0
    for build in ("slabs", "whole"):
        assert main(["export", "--checkpoint", checkpoint, "--out", str(tmp_path / build), "--volume", build]) == 0
    assert asked == ["sweep", "slabs", "whole"]


@pytest.mark.slow
def test_export_writes_the_sweep_graphs_unless_asked_for_another_build(tmp_path):
    save_checkpoint(tmp_path / "c.pt", random_model(small_config("scnerf"), seed=0), {})
    checkpoint = str(tmp_path / "c.pt")
    assert main(["export", "--checkpoint", checkpoint, "--out", str(tmp_path / "sweep")]) == 0
    for build in ("slabs", "whole"):
        assert main(["export", "--checkpoint", checkpoint, "--out", str(tmp_path / build), "--volume", build]) == 0
    manifests = {build: Manifest.load(tmp_path / build) for build in ("sweep", "slabs", "whole")}
    assert set(manifests["sweep"].graphs) == {"encoder", "cost_conv", "volume_net", "renderer", *GUIDED_GRAPHS}
    assert set(manifests["slabs"].graphs) == {"encoder", "cost_slab", "volume_net", "renderer", *GUIDED_GRAPHS}
    assert set(manifests["whole"].graphs) == {"encoder", "volume", "renderer", *GUIDED_GRAPHS}
    assert all(m.model_id == m.expected_model_id() for m in manifests.values())
    assert len({m.model_id for m in manifests.values()}) == 3
