"""scnerf_export.export.volume_tail: ``volume_net.onnx`` without G2's last step gives, with the
server's last step (``volume_from_tail``), the volume of the graph it was rewritten from; and
``scnerf-export volume-tail`` rewrites a bundle's graph in place."""

import shutil

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch

from scnerf_export.cli import main
from scnerf_export.config import small_config
from scnerf_export.export.bundle import example_inputs, graph_modules, graph_signatures, rename_dims, traced_graph
from scnerf_export.export.manifest import Manifest
from scnerf_export.export.volume_tail import PHASES, PHASES_AFFINE, SKIP_AFFINE, TailNotFound, tail_in_server
from scnerf_export.model.checkpoint import sha256_file
from scnerf_export.model.layers import BatchStatNorm
from scnerf_export.rigs import random_model
from scnerf_export.runtime.volume_slabs import run_volume_net, volume_from_tail

from conftest import REPO

FIXTURES = REPO / "tests" / "fixtures"
# Slab graphs as earlier exporters wrote them: volume_net.onnx ends in the volume, its norms chains
# of operators.
OLD_FORM_SLABS = FIXTURES / "g2-readback" / "slabs"


@pytest.fixture(scope="module")
def g2_ending_in_the_graph() -> onnx.ModelProto:
    """``volume_net`` as torch exports it (the volume its output), from a model whose norms have
    scales and shifts of their own: equal constants are shared between norms in the graph, which
    would hide a norm read in place of another."""
    model = random_model(small_config("scnerf"), seed=0)
    rng = np.random.default_rng(0)
    with torch.no_grad():
        for module in model.volume_net.modules():
            if isinstance(module, BatchStatNorm):
                module.weight.copy_(torch.from_numpy(rng.uniform(0.5, 1.5, module.weight.shape)))
                module.bias.copy_(torch.from_numpy(rng.normal(0.0, 0.5, module.bias.shape)))
    g2 = traced_graph(graph_modules(model)["volume_net"], example_inputs(model)["volume_net"], model, "volume_net")
    inputs = graph_signatures(model)["volume_net"]["inputs"]
    rename_dims(g2, {"inputs": inputs, "outputs": {"volume": inputs["conv0"]}})
    return g2


def session(model: onnx.ModelProto) -> ort.InferenceSession:
    return ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])


def test_the_server_step_gives_the_volume_of_the_graph_it_was_cut_from(g2_ending_in_the_graph):
    whole = g2_ending_in_the_graph
    cut = onnx.ModelProto()
    cut.CopyFrom(whole)
    slope = small_config("scnerf").activation_slope
    tail_in_server(cut, slope)
    onnx.checker.check_model(cut, full_check=True)
    assert [o.name for o in cut.graph.output] == [PHASES, SKIP_AFFINE, PHASES_AFFINE]
    depth_to_space = [n for n in cut.graph.node if n.op_type == "DepthToSpace"]
    assert len(depth_to_space) == 2, "the interleaves of the two up blocks before the last stay"
    rng = np.random.default_rng(1)
    for planes, h, w in [(32, 24, 40), (32, 40, 32)]:  # h + 2·pad, w + 2·pad (pad 8)
        conv0 = rng.normal(0.5, 2.0, (1, 8, planes, h, w)).astype(np.float32)
        want = session(whole).run(None, {"conv0": conv0})[0]
        got = run_volume_net(session(cut), conv0, slope)
        assert got.shape == want.shape
        np.testing.assert_allclose(got, want, atol=1e-5 * np.abs(want).max())


def test_the_server_step_refuses_a_slope_that_is_not_a_leaky_relus():
    with pytest.raises(ValueError, match="slope is in"):
        volume_from_tail(np.zeros((1, 8, 2, 2, 2), np.float32), {}, 1.5)


def test_a_graph_that_does_not_end_as_g2_is_refused(g2_ending_in_the_graph):
    slope = small_config("scnerf").activation_slope
    other_slope = onnx.ModelProto()
    other_slope.CopyFrom(g2_ending_in_the_graph)
    with pytest.raises(TailNotFound, match=r"slopes \[0.0099999\d*\] are not the config's 0.2"):
        tail_in_server(other_slope, 0.2)
    cut = onnx.ModelProto()
    cut.CopyFrom(g2_ending_in_the_graph)
    tail_in_server(cut, slope)
    with pytest.raises(TailNotFound, match="no volume output"):
        tail_in_server(cut, slope)
    subtracted = onnx.ModelProto()
    subtracted.CopyFrom(g2_ending_in_the_graph)
    next(n for n in subtracted.graph.node if "volume" in n.output).op_type = "Sub"
    with pytest.raises(TailNotFound, match="volume is not a sum"):
        tail_in_server(subtracted, slope)
    # Norms written as the chain of operators older exporters wrote are not taken apart.
    with pytest.raises(TailNotFound, match="is not a leaky ReLU of a BatchNormalization"):
        tail_in_server(onnx.load(str(OLD_FORM_SLABS / "volume_net.onnx")), slope)


def bundle_ending_g2_in_the_graph(tmp_path, g2: onnx.ModelProto):
    """The parity bundle with its volume built by the plane sweep, with ``g2`` as volume_net.onnx."""
    out = tmp_path / "bundle"
    out.mkdir()
    shutil.copyfile(FIXTURES / "parity-sweep" / "manifest.json", out / "manifest.json")
    manifest = Manifest.load(out)
    for name, entry in manifest.graphs.items():
        split = FIXTURES / "parity-sweep" / entry.file
        if name != "volume_net":
            shutil.copyfile(split if split.is_file() else FIXTURES / "parity" / "bundle" / entry.file, out / entry.file)
    onnx.save(g2, str(out / "volume_net.onnx"))
    entry = manifest.graphs["volume_net"]
    entry.outputs = Manifest.load(OLD_FORM_SLABS).graphs["volume_net"].outputs
    entry.sha256 = sha256_file(out / "volume_net.onnx")
    manifest.save(out)
    return out


def test_volume_tail_rewrites_a_bundle_in_place_once(tmp_path, capsys, g2_ending_in_the_graph):
    bundle = bundle_ending_g2_in_the_graph(tmp_path, g2_ending_in_the_graph)
    before = Manifest.load(bundle)
    assert main(["volume-tail", "--bundle", str(bundle)]) == 0
    assert "agrees with the old graph's" in capsys.readouterr().out
    after = Manifest.load(bundle)
    assert after.model_id == after.expected_model_id() != before.model_id
    assert [t.name for t in after.graphs["volume_net"].outputs] == [PHASES, SKIP_AFFINE, PHASES_AFFINE]
    assert after.provenance.extra["volume_tail"]["volume_max_abs_difference"] <= 1e-4
    assert after.graphs["volume_net"].sha256 == sha256_file(bundle / "volume_net.onnx")
    assert not (bundle / "volume_net.rewritten.onnx").exists()
    assert main(["volume-tail", "--bundle", str(bundle)]) == 2
    assert "already leaves G2's last step to the server" in capsys.readouterr().err
