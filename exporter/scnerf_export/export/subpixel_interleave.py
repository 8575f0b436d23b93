"""G2's sub-pixel interleave as ONNX Runtime runs it fast.

``transposed_conv_as_subpixel`` (model/cost_volume.py) ends with one Transpose, perm
(0, 4, 1, 5, 2, 6, 3), of (Co, rz, ry, rx, d, h, w) into (Co, d, rz, h, ry, w, rx): each output
row interleaves two input rows value by value. ONNX Runtime's Transpose does that one value at a
time (a third of ``volume_net.onnx``'s time at 640x512). The same permutation in two steps:

1. Transpose to (Co, d, rz, ry, rx, h, w): the rows stay whole, copied as blocks;
2. DepthToSpace (CRD, block 2) of (Co·d·rz, ry·rx, h, w) into (Co·d·rz, 1, 2h, 2w), whose kernel
   interleaves whole rows.

Both only move values: the output is the original Transpose's, bit for bit. The pass takes every
Transpose of that 7-D perm to be such an interleave (sizes 2 on axes 1-3), as in G2's graphs;
each exported graph is checked against PyTorch after it.
"""

from __future__ import annotations

import onnx
from onnx import TensorProto, helper

INTERLEAVE = [0, 4, 1, 5, 2, 6, 3]
BLOCKS_FIRST = [0, 4, 1, 2, 3, 5, 6]


def interleaves_as_depth_to_space(model: onnx.ModelProto) -> int:
    """Rewrites every Transpose of perm ``INTERLEAVE`` in place; returns how many."""
    graph = model.graph
    rewritten = []
    for k, node in enumerate(graph.node):
        perm = next((list(a.ints) for a in node.attribute if a.name == "perm"), None)
        if node.op_type == "Transpose" and perm == INTERLEAVE:
            rewritten.append((k, node))
    for k, node in reversed(rewritten):
        graph.node.remove(node)
        for offset, new in enumerate(_depth_to_space_nodes(graph, node.input[0], node.output[0])):
            graph.node.insert(k + offset, new)
    return len(rewritten)


def _depth_to_space_nodes(graph: onnx.GraphProto, x: str, out: str) -> list[onnx.NodeProto]:
    """Nodes that compute ``Transpose(x, INTERLEAVE)`` into ``out``; their constants go into the
    graph's initializers."""
    p = f"{out}_interleave_"
    graph.initializer.extend(
        [
            helper.make_tensor(p + "lead", TensorProto.INT64, [2], [-1, 4]),
            helper.make_tensor(p + "order", TensorProto.INT64, [7], INTERLEAVE),
        ]
    )
    return [
        helper.make_node("Transpose", [x], [p + "blocks"], perm=BLOCKS_FIRST),
        helper.make_node("Shape", [x], [p + "shape"]),
        helper.make_node("Shape", [x], [p + "hw"], start=5),
        helper.make_node("Concat", [p + "lead", p + "hw"], [p + "planes_shape"], axis=0),
        helper.make_node("Reshape", [p + "blocks", p + "planes_shape"], [p + "planes"]),
        helper.make_node("DepthToSpace", [p + "planes"], [p + "rows"], blocksize=2, mode="CRD"),
        helper.make_node("Gather", [p + "shape", p + "order"], [p + "out_shape"], axis=0),
        helper.make_node("Reshape", [p + "rows", p + "out_shape"], [out]),
    ]
