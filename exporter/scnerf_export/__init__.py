"""SC-NeRF exporter: the PyTorch network, public-checkpoint import, ONNX sub-graphs, evaluation."""

__version__ = "0.3.0"
