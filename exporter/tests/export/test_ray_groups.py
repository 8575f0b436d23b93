"""scnerf_export.export.ray_groups: the attention core in a Loop over ray groups computes exactly what
the plain chain computes, for every ray count, and nothing else in a graph is touched."""

import numpy as np
import onnx
import onnxruntime as ort
import pytest
from onnx import TensorProto, helper

from scnerf_export.export.ray_groups import attention_cores_in_ray_groups, plain_attention_cores

HEADS, HEAD_DIM, TOKENS = 2, 3, 5


def chain_model(extra_softmax: bool = False) -> onnx.ModelProto:
    """MatMul(q, k) -> Softmax -> Transpose -> MatMul(v, .) as the exporter writes it; optionally
    a second Softmax that feeds no such chain."""
    nodes = [
        helper.make_node("MatMul", ["q", "k"], ["scores"], name="scores"),
        helper.make_node("Softmax", ["scores"], ["attention"], name="softmax", axis=-1),
        helper.make_node("Transpose", ["attention"], ["attention_t"], name="transpose", perm=[0, 1, 3, 2]),
        helper.make_node("MatMul", ["v", "attention_t"], ["y"], name="values"),
    ]
    outputs = [helper.make_tensor_value_info("y", TensorProto.FLOAT, ["R", HEADS, HEAD_DIM, TOKENS])]
    if extra_softmax:
        nodes.append(helper.make_node("Softmax", ["q"], ["q_softmax"], name="other", axis=-1))
        outputs.append(helper.make_tensor_value_info("q_softmax", TensorProto.FLOAT, None))
    graph = helper.make_graph(
        nodes,
        "chain",
        [
            helper.make_tensor_value_info("q", TensorProto.FLOAT, ["R", 1, TOKENS, 2]),
            helper.make_tensor_value_info("k", TensorProto.FLOAT, ["R", HEADS, 2, TOKENS]),
            helper.make_tensor_value_info("v", TensorProto.FLOAT, ["R", HEADS, HEAD_DIM, TOKENS]),
        ],
        outputs,
    )
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 20)], ir_version=10)


def run(model: onnx.ModelProto, rays: int, seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    feeds = {
        "q": rng.standard_normal((rays, 1, TOKENS, 2), np.float32),
        "k": rng.standard_normal((rays, HEADS, 2, TOKENS), np.float32) * 3,
        "v": rng.standard_normal((rays, HEADS, HEAD_DIM, TOKENS), np.float32),
    }
    session = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
    return session.run(None, feeds)


@pytest.mark.parametrize("rays", [1, 3, 4, 5, 8, 13])
def test_grouped_core_equals_the_chain_for_every_ray_count(rays):
    plain = chain_model()
    grouped = chain_model()
    assert attention_cores_in_ray_groups(grouped, rays_per_group=4) == 1
    onnx.checker.check_model(grouped, full_check=True)
    assert [n.op_type for n in grouped.graph.node].count("Loop") == 1
    (want,), (got,) = run(plain, rays), run(grouped, rays)
    assert got.shape == want.shape == (rays, HEADS, HEAD_DIM, TOKENS)
    np.testing.assert_array_equal(got, want)  # same maths in the same order: not merely close


def test_nodes_without_names_are_rewritten_alike():
    plain, grouped = chain_model(extra_softmax=True), chain_model(extra_softmax=True)
    for node in grouped.graph.node:
        node.name = ""
    assert attention_cores_in_ray_groups(grouped, rays_per_group=4) == 1
    assert [n.op_type for n in grouped.graph.node].count("Softmax") == 2  # the rest's copy and the other one
    for g, w in zip(run(grouped, 9), run(plain, 9)):
        np.testing.assert_array_equal(g, w)


def test_a_softmax_outside_the_chain_is_left_alone():
    grouped = chain_model(extra_softmax=True)
    assert attention_cores_in_ray_groups(grouped, rays_per_group=4) == 1
    assert "other" in [n.name for n in grouped.graph.node]
    want, got = run(chain_model(extra_softmax=True), 6), run(grouped, 6)
    for g, w in zip(got, want):
        np.testing.assert_array_equal(g, w)


def test_a_graph_without_the_chain_is_unchanged():
    model = chain_model()
    model.graph.node[2].op_type = "Identity"  # softmax -> identity -> matmul: not an attention core
    del model.graph.node[2].attribute[:]
    before = model.SerializeToString()
    assert attention_cores_in_ray_groups(model) == 0
    assert model.SerializeToString() == before


def test_the_inverse_rewrite_restores_the_plain_chain():
    original, model = chain_model(extra_softmax=True), chain_model(extra_softmax=True)
    attention_cores_in_ray_groups(model, rays_per_group=4)
    assert plain_attention_cores(model) == 1
    assert list(model.graph.node) == list(original.graph.node)
