"""G2's last step in the server: ``volume_net.onnx`` returns the phases of the last up block and
the affine maps of the two norms that end G2; the server interleaves, normalises, activates and
adds them in one pass as it writes the volume.

G2 ends with ``V = σ(N0(conv0)) + σ(N11(interleave(P)))``: σ the leaky ReLU, N a norm with the
volume's statistics, P the 8·C sub-pixel phases of conv11 (``transposed_conv_as_subpixel``).
In ONNX Runtime each operator of that sum writes a tensor of the volume's size (150 MB for
640x512 sources), a fresh mapping that is faulted in page by page: the interleave, the squares
for the statistics, the norm, the activation and the sum took a third of the graph's run
(docs/results.md, "The volume build"). A norm is per channel and the interleave a
permutation, so N11's statistics are those of P with the 8 phases of each channel taken together,
and each norm is ``x·scale + shift`` per channel once they are known.

The rewritten graph outputs (docs/bundle.md, ``volume_net.onnx``):

- ``phases`` (1, 8·C, D/2, Hp/2, Wp/2): channel ``8c + 4i + 2j + k`` holds the volume's cells
  (2z + i, 2y + j, 2x + k) of channel c before N11;
- ``skip_affine`` and ``phases_affine`` (2, C): each norm's scale (row 0) and shift (row 1).
"""

from __future__ import annotations

import numpy as np
import onnx
from onnx import TensorProto, helper

from . import onnx_graph

PHASES, SKIP_AFFINE, PHASES_AFFINE = "phases", "skip_affine", "phases_affine"
# What lies between conv11's convolution and the interleaved tensor N11 reads: the interleave,
# in either form the exporter writes (one Transpose, or Transpose + DepthToSpace).
_INTERLEAVE_OPS = ("Reshape", "Transpose", "DepthToSpace")


class TailNotFound(ValueError):
    """The graph does not end as G2 does; one line, fit for a CLI."""


def tail_in_server(model: onnx.ModelProto, slope: float) -> None:
    """Rewrites ``volume_net``'s end in place (``volume`` = σ(N0(``conv0``)) +
    σ(N11(interleave(P)))). The server takes σ's slope from the config: the graph's must be
    ``slope``."""
    input_name, output_name = "conv0", "volume"
    graph = model.graph
    nodes = list(graph.node)
    producer, consumer = onnx_graph.producers(nodes), onnx_graph.consumers(nodes)
    if output_name not in producer:
        raise TailNotFound(f"no {output_name} output")
    total = nodes[producer[output_name]]
    if total.op_type != "Add":
        raise TailNotFound(f"{output_name} is not a sum")
    branches = [_activated_norm(nodes, producer, name) for name in total.input]
    skip = next((b for b in branches if b[1].input[0] == input_name), None)
    if skip is None or len(branches) != 2:
        raise TailNotFound(f"{output_name} does not add the activated norm of {input_name}")
    up = branches[1 - branches.index(skip)]
    slopes = {np.float32(_attribute(activation, "alpha", 0.01)) for activation, _ in branches}
    if slopes != {np.float32(slope)}:
        raise TailNotFound(f"the leaky ReLUs' slopes {sorted(map(float, slopes))} are not the config's {slope}")
    interleaved = up[1].input[0]
    phases = _phases_before(nodes, producer, interleaved)
    channels = _channels(graph, skip[1])
    planes = next(i for i in graph.input if i.name == input_name).type.tensor_type.shape.dim[2]

    grouped = f"{PHASES}_by_channel"
    graph.initializer.append(helper.make_tensor(f"{grouped}_shape", TensorProto.INT64, [5], [1, channels, -1, 0, 0]))
    graph.node.append(helper.make_node("Reshape", [PHASES, f"{grouped}_shape"], [grouped]))
    for k in consumer.get(interleaved, []):  # N11's statistics, from the phases
        node = nodes[k]
        node.input[:] = [grouped if name == interleaved else name for name in node.input]
    for node in graph.node:
        node.input[:] = [PHASES if name == phases else name for name in node.input]
        node.output[:] = [PHASES if name == phases else name for name in node.output]
    graph.node.extend(_affine_nodes(graph, skip[1], SKIP_AFFINE) + _affine_nodes(graph, up[1], PHASES_AFFINE))

    del graph.output[:]
    half = planes.dim_value // 2 or None
    graph.output.extend(
        [
            helper.make_tensor_value_info(PHASES, TensorProto.FLOAT, [1, 8 * channels, half, None, None]),
            helper.make_tensor_value_info(SKIP_AFFINE, TensorProto.FLOAT, [2, channels]),
            helper.make_tensor_value_info(PHASES_AFFINE, TensorProto.FLOAT, [2, channels]),
        ]
    )
    _keep_only_what_outputs_need(graph)
    onnx_graph.sort_with_outer_scope_reads(graph)


def _activated_norm(nodes, producer, name: str) -> tuple[onnx.NodeProto, onnx.NodeProto]:
    """The LeakyRelu that outputs ``name`` and the BatchNormalization it reads."""
    activation = nodes[producer[name]] if name in producer else None
    norm = nodes[producer[activation.input[0]]] if activation and activation.input[0] in producer else None
    if activation is None or activation.op_type != "LeakyRelu" or norm is None or norm.op_type != "BatchNormalization":
        raise TailNotFound(f"{name} is not a leaky ReLU of a BatchNormalization")
    return activation, norm


def _phases_before(nodes, producer, interleaved: str) -> str:
    """The output of the convolution that ``interleaved`` rearranges."""
    name = interleaved
    while name in producer and nodes[producer[name]].op_type in _INTERLEAVE_OPS:
        name = nodes[producer[name]].input[0]
    if name not in producer or nodes[producer[name]].op_type != "Conv" or name == interleaved:
        raise TailNotFound(f"{interleaved} is not an interleaved convolution output")
    return name


def _channels(graph: onnx.GraphProto, norm: onnx.NodeProto) -> int:
    weight = next((t for t in graph.initializer if t.name == norm.input[1]), None)
    if weight is None or len(weight.dims) != 1:
        raise TailNotFound(f"the norm's scale {norm.input[1]} is not a constant vector")
    return int(weight.dims[0])


def _affine_nodes(graph: onnx.GraphProto, norm: onnx.NodeProto, out: str) -> list[onnx.NodeProto]:
    """Nodes that write ``norm``'s map ``x·scale + shift`` as (2, C) [scale; shift] into ``out``:
    ``scale = γ / sqrt(var + ε)``, ``shift = β - mean·scale``."""
    _, gamma, beta, mean, var = norm.input
    p = f"{out}_"
    graph.initializer.extend(
        [
            helper.make_tensor(p + "eps", TensorProto.FLOAT, [], [_attribute(norm, "epsilon", 1e-5)]),
            helper.make_tensor(p + "row", TensorProto.INT64, [2], [1, -1]),
        ]
    )
    return [
        helper.make_node("Add", [var, p + "eps"], [p + "var_eps"]),
        helper.make_node("Sqrt", [p + "var_eps"], [p + "std"]),
        helper.make_node("Div", [gamma, p + "std"], [p + "scale"]),
        helper.make_node("Mul", [mean, p + "scale"], [p + "mean_scaled"]),
        helper.make_node("Sub", [beta, p + "mean_scaled"], [p + "shift"]),
        helper.make_node("Reshape", [p + "scale", p + "row"], [p + "scale_row"]),
        helper.make_node("Reshape", [p + "shift", p + "row"], [p + "shift_row"]),
        helper.make_node("Concat", [p + "scale_row", p + "shift_row"], [out], axis=0),
    ]


def _attribute(node: onnx.NodeProto, name: str, default: float) -> float:
    return next((a.f for a in node.attribute if a.name == name), default)


def _keep_only_what_outputs_need(graph: onnx.GraphProto) -> None:
    """Drops the nodes no output depends on, the constants no node reads and the recorded shapes of
    intermediate tensors."""
    nodes = list(graph.node)
    producer = onnx_graph.producers(nodes)
    needed, stack, keep = set(), [o.name for o in graph.output], set()
    while stack:
        name = stack.pop()
        if name in needed:
            continue
        needed.add(name)
        if name in producer:
            keep.add(producer[name])
            stack.extend(i for i in nodes[producer[name]].input if i)
    del graph.node[:]
    graph.node.extend(node for k, node in enumerate(nodes) if k in keep)
    kept = [t for t in graph.initializer if t.name in needed]
    del graph.initializer[:]
    graph.initializer.extend(kept)
    # The shapes recorded for the statistics' tensors were the interleaved tensor's.
    del graph.value_info[:]
