"""The exporter writes no graph the server would refuse for external data."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import helper, numpy_helper

from scnerf_export.export.external_data import check_holds_its_weights

REPO = Path(__file__).resolve().parents[3]


def _graph_with_weight(tmp_path: Path, external: bool) -> Path:
    weight = numpy_helper.from_array(np.ones((256, 256), np.float32), "w")
    node = helper.make_node("MatMul", ["x", "w"], ["y"])
    x = helper.make_tensor_value_info("x", onnx.TensorProto.FLOAT, [1, 256])
    y = helper.make_tensor_value_info("y", onnx.TensorProto.FLOAT, [1, 256])
    model = helper.make_model(helper.make_graph([node], "g", [x], [y], [weight]))
    path = tmp_path / "g.onnx"
    onnx.save(model, str(path), save_as_external_data=external, location="weights.bin", size_threshold=0)
    return path


def test_a_graph_with_external_data_is_refused(tmp_path: Path) -> None:
    check_holds_its_weights(_graph_with_weight(tmp_path, external=False))
    with pytest.raises(ValueError, match=r"tensors \['w'\] keep their data in external files"):
        check_holds_its_weights(_graph_with_weight(tmp_path, external=True))


def test_the_committed_bundles_hold_their_weights() -> None:
    graphs = sorted((REPO / "bundles" / "default").glob("*.onnx"))
    assert graphs
    for path in graphs:
        check_holds_its_weights(path)
