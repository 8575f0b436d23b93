"""Walking an ONNX graph's nodes: who makes a tensor, who reads it, what a subgraph reads.

Nodes are told apart by their position in ``graph.node``: a node's name may be empty or repeated.
The graph rewriters (ray_groups), the quantiser's node selection (precision) and the weight reader
of old bundles (reexport) share these.
"""

from __future__ import annotations

import onnx


def producers(nodes) -> dict[str, int]:
    """Tensor name -> position of the node that outputs it."""
    return {out: k for k, node in enumerate(nodes) for out in node.output}


def consumers(nodes) -> dict[str, list[int]]:
    """Tensor name -> positions of the nodes that take it as an explicit input, in graph order."""
    found: dict[str, list[int]] = {}
    for k, node in enumerate(nodes):
        for name in node.input:
            found.setdefault(name, []).append(k)
    return found


def outer_scope_reads(node) -> set[str]:
    """Names the node's subgraphs (a Loop's body) read from the enclosing graph."""
    reads = set()
    for attribute in node.attribute:
        for body in [attribute.g] if attribute.type == onnx.AttributeProto.GRAPH else list(attribute.graphs):
            local = {v.name for v in body.input} | {t.name for t in body.initializer}
            for inner in body.node:
                reads |= {i for i in inner.input if i and i not in local} | (outer_scope_reads(inner) - local)
                local |= set(inner.output)
    return reads


def sort_with_outer_scope_reads(graph: onnx.GraphProto) -> None:
    """Order the nodes so that every node follows the producers of what it and its subgraphs read,
    keeping the given order where it already does. onnxruntime's quantiser sorts by explicit
    inputs only, which puts the renderer's ray-group Loops before the tensors their bodies slice."""
    nodes = list(graph.node)
    producer = producers(nodes)
    reads = [sorted(set(node.input) | outer_scope_reads(node)) for node in nodes]
    placed, order = set(), []
    for k in range(len(nodes)):
        stack = [k]  # depth-first, without recursion: the dependency chains are ~1000 nodes long
        while stack:
            top = stack[-1]
            if top in placed:
                stack.pop()
                continue
            missing = [producer[n] for n in reads[top] if n in producer and producer[n] not in placed]
            if missing:
                stack.extend(missing)
            else:
                placed.add(stack.pop())
                order.append(nodes[top])
    del graph.node[:]
    graph.node.extend(order)
