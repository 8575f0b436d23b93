"""The rectifiers' attention cores of an exported renderer graph, run a group of rays at a time.

Each rectifier's core, scores -> softmax -> values (``SampleAxisAttention``: MatMul, Softmax,
Transpose, MatMul in the graph), makes (R, h, C, C) scores: 64 KiB per ray for the default bundle,
33 MB for a 512-ray run, beyond the 32 MB L3 of the development machine, so each of its three
ops streams them through memory. In an ONNX ``Loop`` over groups of ``RAYS_PER_GROUP`` rays the
scores of a group (2 MiB) stay in the cache from one op to the next, while the rest of the
renderer keeps its long runs (whole runs of 64 rays instead of 512 were within 4 %,
bench/README.md). The products and the order of every sum are the same, so the outputs are
identical to the unrewritten graph's.

The Loop takes the first R - r rays in groups; the remaining r (1..group) rays run through a copy
of the core outside it, so any R >= 1 works and neither path ever sees an empty batch.
"""

from __future__ import annotations

import functools
import re

import onnx
from onnx import TensorProto, helper

from . import onnx_graph

RAYS_PER_GROUP = 32
_GROUP_PREFIX = re.compile(r"^ray_group\d+_")


def attention_cores_in_ray_groups(model: onnx.ModelProto, rays_per_group: int = RAYS_PER_GROUP) -> int:
    """Rewrite every MatMul -> Softmax -> Transpose -> MatMul chain in place; returns how many."""
    graph = model.graph
    nodes = list(graph.node)
    producer, consumers = onnx_graph.producers(nodes), onnx_graph.consumers(nodes)
    cores = [
        core
        for core in (
            _attention_core(nodes, k, producer, consumers) for k, node in enumerate(nodes) if node.op_type == "Softmax"
        )
        if core is not None
    ]
    replacement = {k: [] for core in cores for k in core}
    for g, core in enumerate(cores):
        # The rewritten core takes the place of its last node: all its inputs exist by then.
        replacement[core[-1]] = _grouped([nodes[k] for k in core], f"ray_group{g}_", rays_per_group)
    del graph.node[:]
    graph.node.extend(new for k, node in enumerate(nodes) for new in replacement.get(k, [node]))
    return len(cores)


def plain_attention_cores(model: onnx.ModelProto) -> int:
    """The inverse rewrite: each group back to its plain chain over all R rays at once (the same
    products), e.g. for counting FLOPs by shape inference, which does not look inside a Loop.
    The copy after the loop is the chain with every name prefixed, so unprefixing it restores it."""
    graph = model.graph
    prefixes = sorted({m.group(0) for node in graph.node for out in node.output if (m := _GROUP_PREFIX.match(out))})
    for p in prefixes:
        strip = functools.partial(_unprefixed, prefix=p + "rest_")
        chain = [
            _renamed(node, strip(node.name), strip, strip) for node in graph.node if node.name.startswith(p + "rest_")
        ]
        nodes = list(graph.node)
        # Everything the rewrite made has a prefixed output, except the Concat that writes the
        # chain's own output name; the chain goes back where that Concat was.
        made = [
            k
            for k, node in enumerate(nodes)
            if any(o.startswith(p) for o in node.output) or node.output[0] == chain[-1].output[0]
        ]
        at = made[-1] - (len(made) - 1)
        dropped = set(made)
        kept = [node for k, node in enumerate(nodes) if k not in dropped]
        del graph.node[:]
        graph.node.extend(kept[:at] + chain + kept[at:])
    return len(prefixes)


def _unprefixed(name: str, prefix: str) -> str:
    return name[len(prefix) :] if name.startswith(prefix) else name


def _attention_core(nodes, softmax: int, producer, consumers) -> list[int] | None:
    """Positions of [scores, softmax, transpose, values] when the softmax sits in such a chain."""

    def only_consumer(k):
        users = consumers.get(nodes[k].output[0], [])
        return users[0] if len(users) == 1 else None

    scores = producer.get(nodes[softmax].input[0])
    transpose = only_consumer(softmax)
    values = only_consumer(transpose) if transpose is not None else None
    if (
        scores is None
        or nodes[scores].op_type != "MatMul"
        or only_consumer(scores) != softmax
        or transpose is None
        or nodes[transpose].op_type != "Transpose"
        or values is None
        or nodes[values].op_type != "MatMul"
        or nodes[values].input[1] != nodes[transpose].output[0]
    ):
        return None
    return [scores, softmax, transpose, values]


def _copy(core: list, prefix: str, inputs: dict[str, str]) -> list:
    """The core's nodes with their inputs renamed by `inputs` and their outputs by `prefix`."""
    made = {out for node in core for out in node.output}
    return [
        _renamed(
            node,
            prefix + (node.name or node.output[0]),  # ONNX Runtime refuses two nodes of one name
            lambda i: inputs.get(i, prefix + i if i in made else i),
            lambda o: prefix + o,
        )
        for node in core
    ]


def _renamed(node, name: str, rename_input, rename_output) -> onnx.NodeProto:
    """A copy of the node under `name`, its inputs and outputs renamed by the two functions."""
    copy = onnx.NodeProto()
    copy.CopyFrom(node)
    copy.name = name
    copy.input[:] = [rename_input(i) for i in node.input]
    copy.output[:] = [rename_output(o) for o in node.output]
    return copy


def _ints(name: str, values: list[int]):
    tensor = helper.make_tensor(name, TensorProto.INT64, [len(values)], values)
    return helper.make_node("Constant", [], [name], value=tensor)


def _grouped(core: list, p: str, group: int) -> list:
    """Nodes computing the core's output: a Loop over the groups, the last 1..group rays after it."""
    scores, _, _, values = core
    ray_major = [scores.input[0], scores.input[1], values.input[0]]  # every one has R first
    out = values.output[0]

    in_group = {x: f"{p}group_{x}" for x in ray_major}
    body = helper.make_graph(
        [
            _ints(p + "size", [group]),
            _ints(p + "axis", [0]),
            helper.make_node("Unsqueeze", [p + "i", p + "axis"], [p + "i1"]),
            helper.make_node("Mul", [p + "i1", p + "size"], [p + "start"]),
            helper.make_node("Add", [p + "start", p + "size"], [p + "end"]),
            *[helper.make_node("Slice", [x, p + "start", p + "end", p + "axis"], [in_group[x]]) for x in ray_major],
            *_copy(core, p + "group_", in_group),
            helper.make_node("Identity", [p + "cond"], [p + "cond_out"]),
        ],
        p + "body",
        [
            helper.make_tensor_value_info(p + "i", TensorProto.INT64, []),
            helper.make_tensor_value_info(p + "cond", TensorProto.BOOL, []),
        ],
        [
            helper.make_tensor_value_info(p + "cond_out", TensorProto.BOOL, []),
            helper.make_tensor_value_info(p + "group_" + out, TensorProto.FLOAT, None),
        ],
    )

    rest = {x: f"{p}rest_{x}" for x in ray_major}
    return _named(
        [
            _ints(p + "g", [group]),
            _ints(p + "zero", [0]),
            _ints(p + "one", [1]),
            _ints(p + "minus_one", [-1]),
            _ints(p + "to_last", [2**62]),
            helper.make_node("Shape", [ray_major[-1]], [p + "shape"], end=1),
            helper.make_node("Sub", [p + "shape", p + "one"], [p + "rays_but_one"]),
            helper.make_node("Div", [p + "rays_but_one", p + "g"], [p + "groups1"]),  # (R - 1) // group
            helper.make_node("Squeeze", [p + "groups1", p + "zero"], [p + "groups"]),
            helper.make_node("Mul", [p + "groups1", p + "g"], [p + "in_groups"]),
            helper.make_node(
                "Constant", [], [p + "true"], value=helper.make_tensor(p + "t", TensorProto.BOOL, [], [True])
            ),
            helper.make_node("Loop", [p + "groups", p + "true"], [p + "stacked"], body=body),
            *[helper.make_node("Slice", [x, p + "in_groups", p + "to_last", p + "zero"], [rest[x]]) for x in ray_major],
            *_copy(core, p + "rest_", rest),
            helper.make_node("Shape", [p + "rest_" + out], [p + "item_shape"], start=1),
            helper.make_node("Concat", [p + "minus_one", p + "item_shape"], [p + "flat_shape"], axis=0),
            helper.make_node("Reshape", [p + "stacked", p + "flat_shape"], [p + "grouped"]),
            helper.make_node("Concat", [p + "grouped", p + "rest_" + out], [out], axis=0),
        ]
    )


def _named(nodes: list) -> list:
    """Every new node (and every node of its subgraphs) named after its first output, which is unique."""
    for node in nodes:
        node.name = node.name or f"node_{node.output[0]}"
        for attribute in node.attribute:
            if attribute.type == onnx.AttributeProto.GRAPH:
                _named(attribute.g.node)
    return nodes
