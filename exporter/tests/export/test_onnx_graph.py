"""scnerf_export.export.onnx_graph: producers and readers by position (names may be empty), what a Loop's
body reads from outside, and a topological sort that counts those reads."""

import numpy as np
import onnx
import onnxruntime as ort
from onnx import TensorProto, helper, numpy_helper

from scnerf_export.export import onnx_graph
from scnerf_export.export.precision import products_feeding_softmax


def loop_reading(outer: str, output: str) -> onnx.NodeProto:
    """A Loop of ``n`` iterations whose body only passes the outer-scope tensor ``outer`` on."""
    body = helper.make_graph(
        [helper.make_node("Identity", ["cond_in"], ["cond_out"]), helper.make_node("Identity", [outer], ["each"])],
        "body",
        [
            helper.make_tensor_value_info("i", TensorProto.INT64, []),
            helper.make_tensor_value_info("cond_in", TensorProto.BOOL, []),
        ],
        [
            helper.make_tensor_value_info("cond_out", TensorProto.BOOL, []),
            helper.make_tensor_value_info("each", TensorProto.FLOAT, [3]),
        ],
    )
    return helper.make_node("Loop", ["n", "keep_going"], [output], body=body)


def test_producers_and_consumers_tell_unnamed_nodes_apart():
    nodes = [
        helper.make_node("Relu", ["x"], ["a"]),
        helper.make_node("Neg", ["x"], ["b"]),
        helper.make_node("Add", ["a", "b"], ["c"]),
    ]
    assert onnx_graph.producers(nodes) == {"a": 0, "b": 1, "c": 2}
    assert onnx_graph.consumers(nodes) == {"x": [0, 1], "a": [2], "b": [2]}


def test_outer_scope_reads_are_what_the_body_does_not_make():
    loop = loop_reading("x2", "y")
    assert onnx_graph.outer_scope_reads(loop) == {"x2"}
    assert onnx_graph.outer_scope_reads(helper.make_node("Relu", ["x"], ["a"])) == set()


def test_sort_puts_a_loop_after_the_producer_of_what_its_body_reads():
    graph = helper.make_graph(
        [
            loop_reading("x2", "y"),
            helper.make_node("Neg", ["x"], ["unrelated"]),
            helper.make_node("Mul", ["x", "two"], ["x2"]),
        ],
        "g",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [3])],
        [
            helper.make_tensor_value_info("y", TensorProto.FLOAT, [3, 3]),
            helper.make_tensor_value_info("unrelated", TensorProto.FLOAT, [3]),
        ],
        [
            numpy_helper.from_array(np.array(3, np.int64), "n"),
            numpy_helper.from_array(np.array(True), "keep_going"),
            numpy_helper.from_array(np.array(2.0, np.float32), "two"),
        ],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 20)], ir_version=10)
    onnx_graph.sort_with_outer_scope_reads(model.graph)
    assert [n.op_type for n in model.graph.node] == ["Mul", "Loop", "Neg"]  # the Neg keeps its place after the Loop
    onnx.checker.check_model(model, full_check=True)
    x = np.array([1.0, -2.0, 0.5], np.float32)
    y, _ = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"]).run(None, {"x": x})
    np.testing.assert_array_equal(y, np.stack([2 * x] * 3))


def test_score_products_are_found_through_unnamed_nodes():
    """A weight product reaches the Softmax through several unnamed nodes; a second one does not."""
    weight = numpy_helper.from_array(np.ones((2, 2), np.float32), "w")
    nodes = [
        helper.make_node("MatMul", ["x", "w"], ["s"], name="scores"),
        helper.make_node("Relu", ["s"], ["s1"]),
        helper.make_node("Neg", ["s1"], ["s2"]),
        helper.make_node("Softmax", ["s2"], ["attention"]),
        helper.make_node("MatMul", ["x", "w"], ["t"], name="trunk"),
        helper.make_node("Relu", ["t"], ["t1"]),
    ]
    graph = helper.make_graph(
        nodes,
        "g",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 2])],
        [helper.make_tensor_value_info(n, TensorProto.FLOAT, None) for n in ("attention", "t1")],
        [weight],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 20)])
    assert products_feeding_softmax(model, {"w": weight}) == {"scores"}
