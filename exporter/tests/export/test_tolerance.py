"""The export's check against PyTorch: tolerances relative to the output's scale, and a clear
one-line error (not a traceback) when a graph does not compute what the model does."""

import numpy as np
import pytest
import torch
from torch import nn

from scnerf_export.cli import main
from scnerf_export.export import bundle
from scnerf_export.export.bundle import RELATIVE_TOLERANCE, GraphMismatch, allowed_error, validate_graph


class Scale(nn.Module):
    def __init__(self, factor: float):
        super().__init__()
        self.factor = factor

    def forward(self, x):
        return x * self.factor


def write_graph(module: nn.Module, path, x):
    torch.onnx.export(module, (x,), str(path), input_names=["x"], output_names=["y"], dynamo=False)


def test_small_outputs_keep_the_absolute_bound_large_ones_scale_it():
    assert allowed_error(1e-4, [np.ones(4)]) == 1e-4
    assert allowed_error(1e-4, [np.array([-500.0, 3.0])]) == pytest.approx(500 * RELATIVE_TOLERANCE)


@pytest.mark.filterwarnings("ignore::DeprecationWarning")
def test_a_faithful_graph_passes_and_a_wrong_one_is_one_clear_error(tmp_path):
    # Outputs of magnitude ~400, as a cost volume's.
    x = {"x": torch.full((64,), 400.0) + torch.linspace(0, 1, 64)}
    path = tmp_path / "scale.onnx"
    write_graph(Scale(1.0000001), path, x["x"])
    assert validate_graph(path, Scale(1.0000001), x, tolerance=1e-4) <= allowed_error(1e-4, [x["x"].numpy()])
    with pytest.raises(GraphMismatch, match=r"scale.onnx: ONNX Runtime's output differs from PyTorch's by 0\.4"):
        validate_graph(path, Scale(1.001), x, tolerance=1e-4)


def test_convert_reports_a_mismatch_in_one_line(tmp_path, monkeypatch, capsys):
    def mismatching(*_args, **_kwargs):
        raise bundle.mismatch("cost_slab.onnx: ONNX Runtime's output", 0.5, 0.01)

    monkeypatch.setattr(bundle, "export_bundle", mismatching)
    monkeypatch.setattr("scnerf_export.model.checkpoint.load_mvsnerf", lambda _path: (None, {}))
    assert main(["convert-mvsnerf", "--ckpt", str(tmp_path / "ckpt.tar"), "--out", str(tmp_path / "b")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("scnerf-export convert-mvsnerf: error: cost_slab.onnx: ONNX Runtime's output differs")
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1
