"""`scnerf-export add-guided --bundle DIR`: a bundle's guided-sampling graphs, written from the
weights of its own renderer graph (or from its checkpoint).

Guided sampling (``runtime/guided.py``) runs ``renderer_guide.onnx`` (the renderer at the S
uniform samples, with each ray's weights and rectifier heads) and ``renderer_fine.onnx`` (K given
samples per ray). Both are exported from a PyTorch renderer; a bundle carries no checkpoint, so by
default its weights are read back from its renderer.onnx
(:func:`reexport.renderer_state_from_current_graph`). The guide graph must then render what the
bundle's renderer renders (max abs difference <= 1e-4 in ONNX Runtime on the check rays), which
shows the weights were read right. The renderer and every other graph stay as they are, so the
model id does not change.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import onnxruntime as ort
import torch

from .. import __version__
from ..model.checkpoint import load_checkpoint
from ..model.network import SCNeRF
from ..runtime.volume_slabs import build_volume
from .bundle import CHECK_BLOCKS, CHECK_RAYS, GUIDED_GRAPHS, example_inputs, export_graphs
from .manifest import FLOAT32, GuidedPolicy, Manifest
from .reexport import ReexportError, renderer_state_from_current_graph

AGREEMENT_TOLERANCE = 1e-4


def bundle_encoder(bundle: Path, manifest: Manifest):
    """The bundle's own G1 and G2 in ONNX Runtime, as ``example_inputs``'s ``encode``: the example
    rays then see features and volumes of the scale the renderer was trained on."""
    sessions = {
        name: ort.InferenceSession(str(manifest.graph_path(bundle, name)), providers=["CPUExecutionProvider"])
        for name in manifest.graphs
        if name in ("encoder", "volume", "cost_slab", "cost_conv", "volume_net")
    }
    cfg = manifest.config

    def encode(images, projections, depth_planes):
        (features,) = sessions["encoder"].run(None, {"images": images.numpy()})
        feeds = {"features": features, "images": images.numpy(), "projections": projections.numpy()}
        volume = build_volume(sessions, {**feeds, "depth_planes": depth_planes.numpy()}, cfg)
        return torch.from_numpy(features), torch.from_numpy(volume)

    return encode


def guide_agrees_with_renderer(bundle: Path, examples: dict) -> float:
    """Max abs difference between the guide graph's rgb, depth, opacity and the bundle's renderer's."""
    feeds = {k: v.numpy() for k, v in examples["renderer"].items()}
    run = {
        name: ort.InferenceSession(str(bundle / f"{name}.onnx"), providers=["CPUExecutionProvider"]).run(None, feeds)
        for name in ("renderer", "renderer_guide")
    }
    return max(float(np.abs(a - b).max()) for a, b in zip(run["renderer"], run["renderer_guide"][:3]))


def add_guided(
    bundle_dir: str | Path, out_dir: str | Path | None = None, checkpoint: str | Path | None = None
) -> Manifest:
    src = Path(bundle_dir)
    out = Path(out_dir) if out_dir else src
    manifest = Manifest.load(src)
    if manifest.precision != FLOAT32:
        raise ReexportError(f"{src}: a {manifest.precision} bundle; add the graphs to its float32 source")
    cfg = manifest.config
    if checkpoint:
        model, _ = load_checkpoint(checkpoint)
        if model.cfg != cfg:
            raise ReexportError(f"{checkpoint}: its config differs from the bundle's")
    else:
        model = SCNeRF(cfg).eval()
        model.renderer.load_state_dict(renderer_state_from_current_graph(manifest.graph_path(src, "renderer"), model))
    if out.resolve() != src.resolve():
        shutil.copytree(src, out, dirs_exist_ok=True)
    encode = bundle_encoder(src, manifest)
    examples = (
        example_inputs(model, encode=encode),
        example_inputs(model, blocks=CHECK_BLOCKS, rays=CHECK_RAYS, encode=encode),
    )
    graphs, errors = export_graphs(model, out, GUIDED_GRAPHS, examples)
    agreement = guide_agrees_with_renderer(out, examples[1])
    if not agreement <= AGREEMENT_TOLERANCE:
        for entry in graphs.values():
            (out / entry.file).unlink()
        raise ReexportError(f"{src}: the guide graph differs from the bundle's renderer by {agreement:.3g}")
    manifest.graphs.update(graphs)
    manifest.model_id = manifest.expected_model_id()
    manifest.guided = GuidedPolicy.for_model(cfg)
    manifest.provenance.guided_graphs = {
        "exporter_version": __version__,
        "weights": str(Path(checkpoint).name) if checkpoint else "read back from renderer.onnx",
        "export_validation_max_abs_error": errors,
        "guide_max_abs_difference_from_renderer": agreement,
    }
    manifest.save(out)
    return manifest
