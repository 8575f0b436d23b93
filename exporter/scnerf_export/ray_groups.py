"""The rectifiers' attention cores of an exported renderer graph, run a group of rays at a time.

Each rectifier's core, scores -> softmax -> values (``SampleAxisAttention``: MatMul, Softmax,
Transpose, MatMul in the graph), makes (R, h, C, C) scores: 64 KiB per ray for the default bundle,
33 MB for a 512-ray run, beyond the 32 MB L3 of the development machine, so each of its three
ops streams them through memory. In an ONNX ``Loop`` over groups of ``RAYS_PER_GROUP`` rays the
scores of a group (2 MiB) stay in the cache from one op to the next. The rest of the renderer
keeps whole runs, where its products are more efficient (whole runs of 64 rays are no faster,
bench/README.md). The maths and the order of every sum are the same, so the outputs are
identical to the unrewritten graph's.

The Loop takes the first R - r rays in groups; the remaining r (1..group) rays run through a copy
of the core outside it, so any R >= 1 works and neither path ever sees an empty batch.
"""
from __future__ import annotations

import onnx
from onnx import TensorProto, helper

RAYS_PER_GROUP = 32


def attention_cores_in_ray_groups(model: onnx.ModelProto, rays_per_group: int = RAYS_PER_GROUP) -> int:
    """Rewrite every MatMul -> Softmax -> Transpose -> MatMul chain in place; returns how many."""
    graph = model.graph
    producers = {out: node for node in graph.node for out in node.output}
    consumers: dict[str, list] = {}
    for node in graph.node:
        for name in node.input:
            consumers.setdefault(name, []).append(node)

    cores = [core for core in (_attention_core(n, producers, consumers) for n in graph.node if n.op_type == "Softmax")
             if core is not None]
    replacement = {node.name: [] for core in cores for node in core}
    for k, core in enumerate(cores):
        # The rewritten core takes the place of its last node: all its inputs exist by then.
        replacement[core[-1].name] = _grouped(core, f"ray_group{k}_", rays_per_group)
    nodes = [new for node in graph.node for new in replacement.get(node.name, [node])]
    del graph.node[:]
    graph.node.extend(nodes)
    return len(cores)


def _attention_core(softmax, producers, consumers) -> list | None:
    """[scores, softmax, transpose, values] when softmax sits in such a chain, else None."""
    def only_consumer(node):
        users = consumers.get(node.output[0], [])
        return users[0] if len(users) == 1 else None

    scores = producers.get(softmax.input[0])
    transpose = only_consumer(softmax)
    values = only_consumer(transpose) if transpose is not None else None
    if (scores is None or scores.op_type != "MatMul" or len(consumers[scores.output[0]]) != 1
            or transpose is None or transpose.op_type != "Transpose"
            or values is None or values.op_type != "MatMul" or values.input[1] != transpose.output[0]):
        return None
    return [scores, softmax, transpose, values]


def _copy(core: list, prefix: str, inputs: dict[str, str]) -> list:
    """The core's nodes with their inputs renamed by `inputs` and their outputs by `prefix`."""
    made = {out for node in core for out in node.output}
    copies = []
    for node in core:
        copy = onnx.NodeProto()
        copy.CopyFrom(node)
        copy.name = prefix + node.name
        copy.input[:] = [inputs.get(i, prefix + i if i in made else i) for i in node.input]
        copy.output[:] = [prefix + o for o in node.output]
        copies.append(copy)
    return copies


def _ints(name: str, values: list[int]):
    return helper.make_node("Constant", [], [name], value=helper.make_tensor(name, TensorProto.INT64, [len(values)], values))


def _grouped(core: list, p: str, group: int) -> list:
    """Nodes computing the core's output: a Loop over the groups, the last 1..group rays after it."""
    scores, _, _, values = core
    ray_major = [scores.input[0], scores.input[1], values.input[0]]  # every one has R first
    out = values.output[0]

    in_group = {x: f"{p}group_{x}" for x in ray_major}
    body = helper.make_graph(
        [_ints(p + "size", [group]), _ints(p + "axis", [0]),
         helper.make_node("Unsqueeze", [p + "i", p + "axis"], [p + "i1"]),
         helper.make_node("Mul", [p + "i1", p + "size"], [p + "start"]),
         helper.make_node("Add", [p + "start", p + "size"], [p + "end"]),
         *[helper.make_node("Slice", [x, p + "start", p + "end", p + "axis"], [in_group[x]]) for x in ray_major],
         *_copy(core, p + "group_", in_group),
         helper.make_node("Identity", [p + "cond"], [p + "cond_out"])],
        p + "body",
        [helper.make_tensor_value_info(p + "i", TensorProto.INT64, []),
         helper.make_tensor_value_info(p + "cond", TensorProto.BOOL, [])],
        [helper.make_tensor_value_info(p + "cond_out", TensorProto.BOOL, []),
         helper.make_tensor_value_info(p + "group_" + out, TensorProto.FLOAT, None)])

    rest = {x: f"{p}rest_{x}" for x in ray_major}
    return _named([
        _ints(p + "g", [group]), _ints(p + "zero", [0]), _ints(p + "one", [1]), _ints(p + "minus_one", [-1]),
        _ints(p + "to_last", [2 ** 62]),
        helper.make_node("Shape", [ray_major[-1]], [p + "shape"], end=1),
        helper.make_node("Sub", [p + "shape", p + "one"], [p + "rays_but_one"]),
        helper.make_node("Div", [p + "rays_but_one", p + "g"], [p + "groups1"]),  # (R - 1) // group
        helper.make_node("Squeeze", [p + "groups1", p + "zero"], [p + "groups"]),
        helper.make_node("Mul", [p + "groups1", p + "g"], [p + "in_groups"]),
        helper.make_node("Constant", [], [p + "true"], value=helper.make_tensor(p + "t", TensorProto.BOOL, [], [True])),
        helper.make_node("Loop", [p + "groups", p + "true"], [p + "stacked"], body=body),
        *[helper.make_node("Slice", [x, p + "in_groups", p + "to_last", p + "zero"], [rest[x]]) for x in ray_major],
        *_copy(core, p + "rest_", rest),
        helper.make_node("Shape", [p + "rest_" + out], [p + "item_shape"], start=1),
        helper.make_node("Concat", [p + "minus_one", p + "item_shape"], [p + "flat_shape"], axis=0),
        helper.make_node("Reshape", [p + "stacked", p + "flat_shape"], [p + "grouped"]),
        helper.make_node("Concat", [p + "grouped", p + "rest_" + out], [out], axis=0),
    ])


def _named(nodes: list) -> list:
    """Every new node (and every node of its subgraphs) named after its first output, which is unique."""
    for node in nodes:
        node.name = node.name or f"node_{node.output[0]}"
        for attribute in node.attribute:
            if attribute.type == onnx.AttributeProto.GRAPH:
                _named(attribute.g.node)
    return nodes
