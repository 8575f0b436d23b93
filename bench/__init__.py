"""Benchmarks of a bundle: PyTorch eager, ONNX Runtime from Python and the Rust server, run from the
repository root with the project's venv (README.md):

    .venv/bin/python -m bench --bundle bundles/default --sizes 160x128,320x256

runner (the command line and the measurement plan), workers (one measurement per child process),
scene (the benchmark scene and its inputs), server (the server over HTTP), flops (the renderer's
FLOPs from its ONNX graph), profile (ONNX Runtime's profiles), report (figures derived and the
table). ab, attention_core and chunk_profile are experiments of their own (python -m bench.ab ...).
"""

from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
