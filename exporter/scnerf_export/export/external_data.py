"""The server refuses a graph whose tensors keep their data in external files (``weights.bin``
beside the ``.onnx``; docs/bundle.md): ONNX Runtime would map them, and the manifest's sha256
covers the graph file alone. Every tool that writes a graph into a bundle checks it here."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import onnx


def check_holds_its_weights(path: Path) -> None:
    """Raises ``ValueError`` naming the tensors of the graph at ``path`` whose data lies outside it."""
    proto = onnx.load(str(path), load_external_data=False)
    external = [t.name for t in _tensors(proto.graph) if _is_external(t)]
    for function in proto.functions:
        external += [t.name for node in function.node for t in _node_tensors(node) if _is_external(t)]
    if external:
        raise ValueError(
            f"{path.name}: tensors {external[:3]} keep their data in external files; a bundle's graphs "
            "must hold their weights (the server refuses external data)"
        )


def _is_external(tensor: onnx.TensorProto) -> bool:
    return tensor.data_location == onnx.TensorProto.EXTERNAL or len(tensor.external_data) > 0


def _tensors(graph: onnx.GraphProto) -> Iterator[onnx.TensorProto]:
    yield from graph.initializer
    for sparse in graph.sparse_initializer:
        yield from (sparse.values, sparse.indices)
    for node in graph.node:
        yield from _node_tensors(node)


def _node_tensors(node: onnx.NodeProto) -> Iterator[onnx.TensorProto]:
    for attribute in node.attribute:
        if attribute.HasField("t"):
            yield attribute.t
        yield from attribute.tensors
        for sparse in [attribute.sparse_tensor, *attribute.sparse_tensors]:
            yield from (sparse.values, sparse.indices)
        for graph in [attribute.g, *attribute.graphs]:
            yield from _tensors(graph)
