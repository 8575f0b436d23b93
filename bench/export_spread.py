"""How far each exported graph of a checkpoint lands from PyTorch, across thread counts:
``python -m bench.export_spread --ckpt ../shared/weights/mvsnerf-v0.tar --out DIR``.

Exports the encoder, cost slab, volume net and renderer of the converted public MVSNeRF
checkpoint into DIR and runs each on the export's two sets of check inputs with torch at 1 and 2
threads and ONNX Runtime at 1, 2 and 4; prints one JSON line per run: the max abs difference,
the output's scale (its largest magnitude) and their ratio, from which the export's relative
tolerance is set (docs/results.md, "Export tolerances").
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import onnxruntime as ort
import torch

from scnerf_export.export.bundle import CHECK_BLOCKS, CHECK_RAYS, example_inputs, export_graph, graph_modules
from scnerf_export.model.checkpoint import load_mvsnerf

GRAPHS = ("encoder", "cost_slab", "volume_net", "renderer")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--ckpt", required=True, type=Path)
    parser.add_argument("--out", required=True, type=Path)
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    model = load_mvsnerf(args.ckpt)[0].eval()
    examples = (example_inputs(model), example_inputs(model, blocks=CHECK_BLOCKS, rays=CHECK_RAYS))
    modules = graph_modules(model)
    for name in GRAPHS:
        path = args.out / f"{name}.onnx"
        export_graph(modules[name], examples[0][name], model, name, path)
        for index, example in enumerate(examples):
            for torch_threads in (1, 2):
                torch.set_num_threads(torch_threads)
                with torch.no_grad():
                    want = modules[name](*example[name].values())
                want = [w.numpy() for w in (want if isinstance(want, (tuple, list)) else (want,))]
                for ort_threads in (1, 2, 4):
                    options = ort.SessionOptions()
                    options.intra_op_num_threads = ort_threads
                    session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
                    got = session.run(None, {k: v.numpy() for k, v in example[name].items()})
                    error = max(float(np.abs(g - w).max()) for g, w in zip(got, want))
                    scale = max(float(np.abs(w).max()) for w in want)
                    row = {"graph": name, "inputs": index + 1, "torch_threads": torch_threads}
                    row |= {"ort_threads": ort_threads, "error": error, "scale": scale, "relative": error / scale}
                    print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
