"""From the PyTorch network to the bundle the server runs: the three ONNX sub-graphs and their
manifest (bundle, manifest), the rewrites of exported graphs (ray_groups, precision, reexport, on
the node walker onnx_graph), and the parity fixtures both test suites check (fixtures)."""
