"""scnerf_export.export.subpixel_interleave: the interleave rewritten as Transpose + DepthToSpace
gives the original Transpose's output bit for bit, for any sizes, and leaves other Transposes."""

import numpy as np
import onnx
import onnxruntime as ort
from onnx import TensorProto, helper

from scnerf_export.export.subpixel_interleave import INTERLEAVE, interleaves_as_depth_to_space

CHANNELS = 3


def interleave_model() -> onnx.ModelProto:
    """The end of a sub-pixel transposed convolution as the exporter writes it, beside a Transpose
    of another perm that must stay."""
    dims = [CHANNELS, 2, 2, 2, "d", "h", "w"]
    graph = helper.make_graph(
        [
            helper.make_node("Transpose", ["x"], ["y"], perm=INTERLEAVE),
            helper.make_node("Transpose", ["x"], ["other"], perm=[1, 0, 2, 3, 4, 5, 6]),
        ],
        "interleave",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, dims)],
        [
            helper.make_tensor_value_info("y", TensorProto.FLOAT, [dims[i] for i in INTERLEAVE]),
            helper.make_tensor_value_info("other", TensorProto.FLOAT, [2, CHANNELS, 2, 2, "d", "h", "w"]),
        ],
    )
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 20)], ir_version=10)


def run(model: onnx.ModelProto, x: np.ndarray) -> list[np.ndarray]:
    session = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
    return session.run(None, {"x": x})


def test_the_rewritten_interleave_is_the_transpose_bit_for_bit():
    model = interleave_model()
    assert interleaves_as_depth_to_space(model) == 1
    onnx.checker.check_model(model, full_check=True)
    ops = [node.op_type for node in model.graph.node]
    assert "DepthToSpace" in ops
    perms = [list(a.ints) for node in model.graph.node for a in node.attribute if a.name == "perm"]
    assert INTERLEAVE not in perms and [1, 0, 2, 3, 4, 5, 6] in perms
    rng = np.random.default_rng(0)
    for d, h, w in [(1, 1, 1), (3, 5, 7), (8, 4, 2)]:
        x = rng.standard_normal((CHANNELS, 2, 2, 2, d, h, w)).astype(np.float32)
        y, other = run(model, x)
        np.testing.assert_array_equal(y, x.transpose(INTERLEAVE))
        np.testing.assert_array_equal(other, x.transpose(1, 0, 2, 3, 4, 5, 6))


def test_a_graph_without_the_interleave_is_left_alone():
    model = interleave_model()
    del model.graph.node[0]
    del model.graph.output[0]
    before = model.SerializeToString()
    assert interleaves_as_depth_to_space(model) == 0
    assert model.SerializeToString() == before
