"""Running a network on a view: the PyTorch reference renderer (reference), a bundle in ONNX
Runtime with the server's stages (onnx_pipeline), and what they share (view; band: the colours of
the pixels a source does not see). The Rust server itself is driven from scnerf_export.serving."""
