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
from ..model.network import SCNeRF
from . import onnx_graph
from .bundle import (
    CHECK_BLOCKS,
    CHECK_RAYS,
    RendererGraph,
    example_inputs,
    export_graph,
    graph_entry,
    graph_signatures,
    validate_graph,
)
from .manifest import FLOAT32, Manifest

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


_SHAPE_OPS = ("Reshape", "Transpose", "Unsqueeze", "Squeeze")


def _constant_operand(node, constants: dict) -> np.ndarray | None:
    found = [constants[n] for n in node.input if n in constants]
    return found[0] if len(found) == 1 else None


def _first_constant_upstream(tensor: str, index: _GraphIndex, op_type: str) -> np.ndarray | None:
    """Walking back from ``tensor`` through shape-only ops: the constant operand of the first
    ``op_type`` node."""
    for _ in range(8):
        if tensor not in index.producers:
            return None
        node = index.nodes[index.producers[tensor]]
        if node.op_type == op_type:
            return _constant_operand(node, index.constants)
        if node.op_type not in _SHAPE_OPS:
            return None
        tensor = node.input[0]
    return None


def _first_constant_downstream(tensor: str, index: _GraphIndex, op_type: str) -> np.ndarray | None:
    """Walking forward from ``tensor`` along its first reader: the constant operand of the first
    ``op_type`` node that has one."""
    for _ in range(8):
        readers = index.consumers.get(tensor, [])
        if not readers:
            return None
        node = index.nodes[readers[0]]
        if node.op_type == op_type:
            value = _constant_operand(node, index.constants)
            if value is not None:
                return value
        tensor = node.output[0]
    return None


def _bias_of_gemm(weight: str, index: _GraphIndex, like: torch.Tensor) -> np.ndarray | None:
    """The bias of a layer whose weight feeds a Gemm: its third operand, or zero when the exporter
    dropped an all-zero bias."""
    readers = [index.nodes[k] for k in index.consumers.get(weight, []) if index.nodes[k].op_type == "Gemm"]
    if len(readers) != 1:
        return None
    operands = list(readers[0].input)
    if len(operands) < 3 or not operands[2]:
        return np.zeros(tuple(like.shape), np.float32)
    return index.constants.get(operands[2])


def rectifier_state_from_folds(rows: np.ndarray, key_bias_term: np.ndarray, output_bias: np.ndarray, cfg) -> dict:
    """W_q, W_k and the biases the current renderer graph folds away, rebuilt from what it keeps.

    The graph holds, per rectifier, rows = [w_i . W_k,i ; b_i . W_k,i] / sqrt(d_k) per head i (w_i
    the row sums of W_q, b_i its bias), the key embedding's bias through them (rows summed times
    the embedding bias) and W_o b_v + b_o. Any W_q, W_k with the same rows compute the same
    attention, so head i keeps W_k's first two rows as its two rows of ``rows`` and W_q picks them
    (row sums sqrt(d_k) e_0, bias sqrt(d_k) e_1); W_v's bias is zero and W_o's bias carries it all."""
    heads, dk, samples = cfg.heads, cfg.head_dim, cfg.samples
    scale = np.sqrt(dk)
    w_q = np.zeros((heads * dk, samples), np.float32)
    b_q = np.zeros(heads * dk, np.float32)
    w_k = np.zeros((heads * dk, samples), np.float32)
    for i in range(heads):
        w_q[i * dk, 0] = scale
        b_q[i * dk + 1] = scale
        w_k[i * dk : i * dk + 2] = rows[2 * i : 2 * i + 2]
    sums = rows.sum(axis=1)
    pivot = int(np.argmax(np.abs(sums)))
    return {
        "w_q.weight": w_q,
        "w_q.bias": b_q,
        "w_k.weight": w_k,
        "w_k.bias": np.zeros(heads * dk, np.float32),
        "w_v.bias": np.zeros(heads * dk, np.float32),
        "w_o.bias": output_bias.reshape(-1),
        "key_embedding.bias": key_bias_term[pivot] / sums[pivot],
    }


def renderer_state_from_current_graph(path: Path, model: SCNeRF) -> dict[str, torch.Tensor]:
    """Every renderer parameter of ``model``'s config, read from a renderer.onnx of this exporter:
    the weights kept under their names, M4's output layer behind its bias, and each rectifier's
    folded constants found from its named weights (:func:`rectifier_state_from_folds`). What the
    folds lose (W_q and W_k apart) is rebuilt to compute the same; ``add-guided`` checks the
    result against the graph it was read from."""
    index = _GraphIndex(onnx.load(str(path)))
    constants = index.constants
    state: dict[str, np.ndarray] = {}
    for key in model.renderer.state_dict():
        if _PREFIX + key in constants:
            state[key] = constants[_PREFIX + key]
    for key in set(model.renderer.state_dict()) - set(state):
        if key.endswith(".bias") and key[: -len("bias")] + "weight" in state:
            state[key] = _bias_of_gemm(
                _PREFIX + key[: -len("bias")] + "weight", index, model.renderer.state_dict()[key]
            )
    out_bias = _PREFIX + "colour_head.out.bias"
    weight = _weight_behind_bias(out_bias, index, "MatMul")
    if weight is not None:
        state["colour_head.out.weight"] = weight.T
    for name in model.renderer.rectifiers():
        prefix = _PREFIX + name + "."
        embedding = [index.nodes[k] for k in index.consumers.get(prefix + "key_embedding.weight", [])]
        output = [index.nodes[k] for k in index.consumers.get(prefix + "w_o.weight", [])]
        if len(embedding) != 1 or len(output) != 1:
            raise ReexportError(f"{path}: the {name} rectifier's weights are not where this exporter puts them")
        rows_t = _first_constant_upstream(embedding[0].input[0], index, "MatMul")
        key_bias = _first_constant_downstream(embedding[0].output[0], index, "Add")
        out_bias_rows = _first_constant_downstream(output[0].output[0], index, "Add")
        if rows_t is None or key_bias is None or out_bias_rows is None:
            raise ReexportError(f"{path}: cannot find the {name} rectifier's folded weights")
        folds = rectifier_state_from_folds(rows_t.T, key_bias, out_bias_rows, model.cfg)
        state.update({name + "." + k: v for k, v in folds.items()})
    expected = model.renderer.state_dict()
    missing = sorted(k for k in expected if state.get(k) is None)
    if missing:
        raise ReexportError(f"{path}: cannot find the renderer parameters {', '.join(missing)} in the graph")
    for key, param in expected.items():
        if tuple(state[key].shape) != tuple(param.shape):
            raise ReexportError(
                f"{path}: {key} has shape {tuple(state[key].shape)}, the config needs {tuple(param.shape)}"
            )
    return {k: torch.tensor(np.asarray(state[k]), dtype=torch.float32) for k in expected}


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


def reexport_bundle(bundle_dir: str | Path, out_dir: str | Path) -> Manifest:
    src, out = Path(bundle_dir), Path(out_dir)
    if src.resolve() == out.resolve():
        raise ReexportError("--out must differ from --bundle")
    manifest = Manifest.load(src)
    version = manifest.provenance.exporter_version
    if version != READABLE_EXPORTER_VERSION or manifest.provenance.reexport is not None:
        raise ReexportError(
            f"{src}: written by scnerf-export {version}; reexport reads the renderer graphs of "
            f"{READABLE_EXPORTER_VERSION} bundles"
        )
    if manifest.precision != FLOAT32:
        raise ReexportError(f"{src}: a {manifest.precision} bundle; re-export its float32 source instead")
    model = SCNeRF(manifest.config).eval()
    old_renderer = manifest.graph_path(src, "renderer")
    model.renderer.load_state_dict(renderer_state_from_graph(old_renderer, model))

    out.mkdir(parents=True, exist_ok=True)
    for name in ("encoder", "volume"):
        shutil.copyfile(manifest.graph_path(src, name), manifest.graph_path(out, name))
    renderer_path = out / "renderer.onnx"
    inputs = example_inputs(model)["renderer"]
    export_graph(RendererGraph(model), inputs, model, "renderer", renderer_path)
    validate_graph(renderer_path, RendererGraph(model), inputs, tolerance=AGREEMENT_TOLERANCE)
    agreement = graphs_agree(src, old_renderer, renderer_path, model)
    if not agreement <= AGREEMENT_TOLERANCE:
        renderer_path.unlink()
        raise ReexportError(f"{src}: the re-exported renderer differs from the bundle's by {agreement:.3g}")

    manifest.graphs["renderer"] = graph_entry(renderer_path, graph_signatures(model)["renderer"])
    previous_id = manifest.model_id
    manifest.model_id = manifest.expected_model_id()
    manifest.provenance.reexport = {
        "exporter_version": __version__,
        "source_model_id": previous_id,
        "renderer_max_abs_difference": agreement,
        "what": "renderer.onnx written again by this exporter from the weights in the source renderer graph; "
        "encoder.onnx and volume.onnx unchanged",
    }
    manifest.save(out)
    return manifest
