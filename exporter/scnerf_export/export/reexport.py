"""`scnerf-export reexport --bundle IN --out OUT`: a 0.1 bundle's renderer written again by this exporter.

A bundle carries no checkpoint, only its graphs; the renderer's weights are read back from the
renderer.onnx that scnerf-export 0.1 wrote, the renderer is exported with this version's graph, and
the two graphs are run side by side in ONNX Runtime on the bundle's own features and volume, at an
image size other than the tracing one: the new graph is kept only if they agree (max abs error
<= 1e-4 on rgb, depth, opacity). encoder.onnx and volume.onnx are copied unchanged; results
measured with the old graph stay with the old bundle. This is how a bundle gets the faster
renderer graph without its training checkpoint.

Weights are found the way exporter 0.1 wrote them: under their parameter names
(``model.renderer.<name>``), or, for a linear layer lowered to ``MatMul(x, W^T) + bias``, as the
constant operand of the product that feeds the ``Add`` of its named bias. The query projection
W_q of a rectifier acts on a token that is constant along the samples, so the graph keeps only
its row sums; they are stored in W_q's first column (the rectifier reads W_q only through them).
Later renderer graphs fold more of the weights into other constants, so only 0.1 bundles are read.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import torch
from onnx import numpy_helper

from .. import __version__
from ..config import ModelConfig
from ..model.checkpoint import sha256_file
from ..model.network import SCNeRF
from . import onnx_graph
from .bundle import (
    CHECK_BLOCKS,
    CHECK_RAYS,
    RendererGraph,
    example_inputs,
    export_graph,
    graph_signatures,
    io_spec,
    validate_graph,
)
from .manifest import model_id, read_manifest, write_manifest

AGREEMENT_TOLERANCE = 1e-4
READABLE_EXPORTER_VERSION = "0.1.0"
_PREFIX = "model.renderer."


class ReexportError(ValueError):
    """The bundle's renderer cannot be read back; the message is one line, fit for a CLI."""


class _GraphIndex:
    """The constants of a renderer graph and who makes and reads each tensor (by node position)."""

    def __init__(self, proto: onnx.ModelProto):
        self.constants = {t.name: numpy_helper.to_array(t) for t in proto.graph.initializer}
        self.nodes = list(proto.graph.node)
        self.producers = onnx_graph.producers(self.nodes)
        self.consumers = onnx_graph.consumers(self.nodes)


def _weight_behind_bias(bias: str, index: _GraphIndex, op_type: str) -> np.ndarray | None:
    """The constant operand of the ``op_type`` node whose output is added to ``bias``."""
    constants = index.constants
    for add in (index.nodes[k] for k in index.consumers.get(bias, [])):
        if add.op_type != "Add":
            continue
        other = add.input[0] if add.input[1] == bias else add.input[1]
        node = index.nodes[index.producers[other]] if other in index.producers else None
        if node is not None and node.op_type == op_type:
            found = [constants[n] for n in node.input if n in constants]
            if len(found) == 1:
                return found[0]
    return None


def renderer_state_from_graph(path: Path, model: SCNeRF) -> dict[str, torch.Tensor]:
    """Every renderer parameter of ``model``'s config, read from a renderer.onnx."""
    index = _GraphIndex(onnx.load(str(path)))
    constants = index.constants
    state = {}
    for key, param in model.renderer.state_dict().items():
        name = _PREFIX + key
        if name in constants:
            value = constants[name]
        elif key.endswith(".weight"):
            bias = name[: -len("weight")] + "bias"
            if key.endswith("w_q.weight"):
                value = _weight_behind_bias(bias, index, "Mul")  # row sums
                if value is not None:
                    value = np.pad(value.reshape(-1, 1), ((0, 0), (0, param.shape[1] - 1)))
            else:
                value = _weight_behind_bias(bias, index, "MatMul")
                value = None if value is None else value.T
        else:
            value = None
        if value is None:
            raise ReexportError(f"{path}: cannot find the renderer parameter {key!r} in the graph")
        if tuple(value.shape) != tuple(param.shape):
            raise ReexportError(f"{path}: {key} has shape {tuple(value.shape)}, the config needs {tuple(param.shape)}")
        state[key] = torch.tensor(value, dtype=torch.float32)
    return state


def _session(path: Path) -> ort.InferenceSession:
    return ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])


def graphs_agree(bundle: Path, old_renderer: Path, new_renderer: Path, model: SCNeRF) -> float:
    """Max abs difference of the two renderers on the bundle's own features and volume."""
    inputs = example_inputs(model, blocks=CHECK_BLOCKS, rays=CHECK_RAYS)
    (features,) = _session(bundle / "encoder.onnx").run(None, {k: v.numpy() for k, v in inputs["encoder"].items()})
    volume_inputs = {k: v.numpy() for k, v in inputs["volume"].items()}
    volume_inputs["features"] = features
    (volume,) = _session(bundle / "volume.onnx").run(None, volume_inputs)
    feeds = {k: v.numpy() for k, v in inputs["renderer"].items()}
    feeds["volume"] = volume
    if "features" in feeds:
        feeds["features"] = features
    old = _session(old_renderer).run(None, feeds)
    new = _session(new_renderer).run(None, feeds)
    return max(float(np.abs(a - b).max()) for a, b in zip(old, new))


def reexport_bundle(bundle_dir: str | Path, out_dir: str | Path) -> dict:
    src, out = Path(bundle_dir), Path(out_dir)
    if src.resolve() == out.resolve():
        raise ReexportError("--out must differ from --bundle")
    manifest = read_manifest(src)
    version = manifest.get("provenance", {}).get("exporter_version")
    if version != READABLE_EXPORTER_VERSION or "reexport" in manifest.get("provenance", {}):
        raise ReexportError(
            f"{src}: written by scnerf-export {version}; reexport reads the renderer graphs of "
            f"{READABLE_EXPORTER_VERSION} bundles"
        )
    if manifest.get("precision", "fp32") != "fp32":
        raise ReexportError(f"{src}: a {manifest['precision']} bundle; re-export its float32 source instead")
    model = SCNeRF(ModelConfig.from_dict(manifest["config"])).eval()
    model.renderer.load_state_dict(renderer_state_from_graph(src / manifest["graphs"]["renderer"]["file"], model))

    out.mkdir(parents=True, exist_ok=True)
    for name in ("encoder", "volume"):
        shutil.copyfile(src / manifest["graphs"][name]["file"], out / manifest["graphs"][name]["file"])
    renderer_path = out / "renderer.onnx"
    inputs = example_inputs(model)["renderer"]
    export_graph(RendererGraph(model), inputs, model, "renderer", renderer_path)
    validate_graph(renderer_path, RendererGraph(model), inputs, tolerance=AGREEMENT_TOLERANCE)
    agreement = graphs_agree(src, src / manifest["graphs"]["renderer"]["file"], renderer_path, model)
    if not agreement <= AGREEMENT_TOLERANCE:
        renderer_path.unlink()
        raise ReexportError(f"{src}: the re-exported renderer differs from the bundle's by {agreement:.3g}")

    signature = graph_signatures(model)["renderer"]
    renderer = manifest["graphs"]["renderer"]
    renderer.update(
        file=renderer_path.name,
        sha256=sha256_file(renderer_path),
        inputs=io_spec(signature["inputs"]),
        outputs=io_spec(signature["outputs"]),
    )
    previous_id = manifest["model_id"]
    manifest["model_id"] = model_id(model.cfg.variant, renderer["sha256"])
    manifest["provenance"]["reexport"] = {
        "exporter_version": __version__,
        "source_model_id": previous_id,
        "renderer_max_abs_difference": agreement,
        "what": "renderer.onnx written again by this exporter from the weights in the source renderer graph; "
        "encoder.onnx and volume.onnx unchanged",
    }
    write_manifest(out, manifest)
    return manifest
