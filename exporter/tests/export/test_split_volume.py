"""`scnerf-export split-volume`: a bundle's volume.onnx as cost_slab.onnx + volume_net.onnx, the
volume built slab by slab of depth planes.

tests/fixtures/parity-slabs holds the two graphs and the manifest that split-volume wrote from the
parity fixture bundle (the encoder and renderer are that bundle's own)."""

import hashlib
import shutil

import numpy as np
import pytest

from scnerf_export.cli import main
from scnerf_export.config import ModelConfig, small_config
from scnerf_export.export.manifest import read_manifest
from scnerf_export.export.split_volume import SplitVolumeError, check_inputs, split_volume_bundle, volumes_agree
from scnerf_export.model.checkpoint import save_checkpoint
from scnerf_export.rigs import random_model
from scnerf_export.runtime.onnx_pipeline import OnnxBundle
from scnerf_export.runtime.volume_slabs import SLAB_BYTES_PER_CELL, build_volume, planes_per_slab

from conftest import REPO

WHOLE = REPO / "tests" / "fixtures" / "parity" / "bundle"
SLABS = REPO / "tests" / "fixtures" / "parity-slabs"


def sha256(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture
def split_bundle(tmp_path):
    """The committed split graphs with the parity bundle's encoder and renderer."""
    out = tmp_path / "slabs"
    out.mkdir()
    for name in ("encoder.onnx", "renderer.onnx"):
        shutil.copyfile(WHOLE / name, out / name)
    for name in ("cost_slab.onnx", "volume_net.onnx", "manifest.json"):
        shutil.copyfile(SLABS / name, out / name)
    return out


def test_the_committed_slab_graphs_give_the_volume_graphs_volume_at_any_slab_size():
    cfg = ModelConfig.from_dict(read_manifest(WHOLE)["config"])
    inputs = check_inputs(WHOLE / "encoder.onnx", cfg)
    assert volumes_agree(WHOLE / "volume.onnx", SLABS, inputs, slab_sizes=(1, 3, 7, cfg.depth_planes)) == 0.0


def test_a_split_bundle_renders_what_the_whole_one_renders(split_bundle):
    whole, slabs = OnnxBundle(WHOLE), OnnxBundle(split_bundle)
    assert set(slabs.sessions) == {"encoder", "cost_slab", "volume_net", "renderer"}
    cfg = whole.cfg
    inputs = check_inputs(WHOLE / "encoder.onnx", cfg)
    _, _, h, w = inputs["features"].shape
    cells = (h + 2 * cfg.pad) * (w + 2 * cfg.pad)
    want = whole.sessions["volume"].run(None, inputs)[0]
    for planes in (1, 4, cfg.depth_planes):
        budget = (planes + 2) * SLAB_BYTES_PER_CELL * cells
        assert planes_per_slab(cfg.depth_planes, cells, budget) == planes
        assert np.array_equal(build_volume(slabs.sessions, inputs, cfg.pad, budget), want)


def test_the_manifest_keeps_the_model_and_names_the_split():
    whole, slabs = read_manifest(WHOLE), read_manifest(SLABS)
    assert slabs["model_id"] == whole["model_id"] and slabs["config"] == whole["config"]
    assert list(slabs["graphs"]) == ["encoder", "cost_slab", "volume_net", "renderer"]
    for name in ("encoder", "renderer"):
        assert slabs["graphs"][name] == whole["graphs"][name]
    for name in ("cost_slab", "volume_net"):
        assert slabs["graphs"][name]["sha256"] == sha256(SLABS / f"{name}.onnx")
    assert slabs["provenance"]["volume_split"]["volume_max_abs_difference"] == 0.0


@pytest.mark.slow
def test_split_volume_writes_graphs_that_agree_with_the_volume_graph(tmp_path):
    out = tmp_path / "out"
    manifest = split_volume_bundle(WHOLE, out)
    assert manifest["provenance"]["volume_split"]["volume_max_abs_difference"] == 0.0
    assert not (out / "volume.onnx").exists()
    for name in ("encoder.onnx", "renderer.onnx"):
        assert (out / name).read_bytes() == (WHOLE / name).read_bytes()
    assert read_manifest(out) == manifest
    # The split bundle is not split again.
    with pytest.raises(SplitVolumeError, match="no volume graph"):
        split_volume_bundle(out, tmp_path / "again")


def test_split_volume_refuses_to_overwrite_its_source_in_one_line(capsys):
    with pytest.raises(SplitVolumeError, match="--out must differ"):
        split_volume_bundle(WHOLE, WHOLE)
    assert main(["split-volume", "--bundle", str(SLABS), "--out", str(SLABS)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("scnerf-export split-volume: error:") and "\n" not in err


def test_export_writes_the_slab_graphs_unless_asked_for_one_volume_graph(tmp_path):
    save_checkpoint(tmp_path / "c.pt", random_model(small_config("scnerf"), seed=0), {})
    assert main(["export", "--checkpoint", str(tmp_path / "c.pt"), "--out", str(tmp_path / "slabs")]) == 0
    assert (
        main(["export", "--checkpoint", str(tmp_path / "c.pt"), "--out", str(tmp_path / "whole"), "--volume", "whole"])
        == 0
    )
    slabs, whole = read_manifest(tmp_path / "slabs"), read_manifest(tmp_path / "whole")
    assert set(slabs["graphs"]) == {"encoder", "cost_slab", "volume_net", "renderer"}
    assert set(whole["graphs"]) == {"encoder", "volume", "renderer"}
    assert slabs["model_id"] == whole["model_id"]
