"""SC-NeRF exporter, in subpackages by stage: model (the network and its checkpoints), export
(bundles, graph rewrites, parity fixtures), data (scene formats and procedural scenes), train,
evaluate, runtime (the PyTorch reference renderer and ONNX Runtime); cameras, config, rigs and
serving are shared by several of them. The command line is cli (``scnerf-export``)."""

__version__ = "0.3.0"
