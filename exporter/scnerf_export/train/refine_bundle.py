"""The bundle side of `scnerf-export refine`: the base bundle's renderer weights in PyTorch, and the
refined bundle written from them.

A bundle carries graphs, not a checkpoint. Refine trains the renderer's weights (M1 and the heads)
and keeps the base bundle's encoder and volume graphs, so it needs the renderer's weights only:
read back from ``renderer.onnx`` (:func:`reexport.renderer_state_from_current_graph`, as
``add-guided`` does) or taken from the bundle's source checkpoint (``--checkpoint``). Either way
the PyTorch renderer must render what the bundle's renderer graph renders (ONNX Runtime, the
bundle's own encoder and volume, at most 1e-4) before anything trains.

The refined bundle is an ordinary one: the base's encoder and volume graphs copied, the renderer
graphs (and the guided-sampling graphs where the base has them) exported from the refined weights
and checked against PyTorch, a new model id, and ``provenance.refinement`` (docs/bundle.md).
"""

from __future__ import annotations

import copy
import datetime as _dt
import os
import shutil
from pathlib import Path

import numpy as np
import onnxruntime as ort
import torch

from ..export.bundle import CHECK_BLOCKS, CHECK_RAYS, GUIDED_GRAPHS, RendererGraph, example_inputs, export_graphs
from ..export.guided import bundle_encoder
from ..export.manifest import FLOAT32, Manifest
from ..export.reexport import ReexportError, renderer_state_from_current_graph
from ..model.checkpoint import load_checkpoint, sha256_file
from ..model.network import SCNeRF

AGREEMENT_TOLERANCE = 1e-4
RENDERER_GRAPHS = ("renderer", *GUIDED_GRAPHS)


class BundleError(ValueError):
    """A base bundle refine cannot start from; the message is one line, fit for a CLI."""


def renderer_agreement(bundle: Path, manifest: Manifest, model: SCNeRF) -> float:
    """Max abs difference between ``model``'s renderer and the bundle's renderer graph, on example
    rays of features and volumes from the bundle's own encoder and volume graphs."""
    inputs = example_inputs(model, blocks=CHECK_BLOCKS, rays=CHECK_RAYS, encode=bundle_encoder(bundle, manifest))
    feeds = inputs["renderer"]
    session = ort.InferenceSession(str(manifest.graph_path(bundle, "renderer")), providers=["CPUExecutionProvider"])
    graph = session.run(None, {k: v.numpy() for k, v in feeds.items()})
    with torch.no_grad():
        eager = RendererGraph(model)(*feeds.values())
    return max(float(np.abs(a - b.numpy()).max()) for a, b in zip(graph, eager))


def _weights(bundle: Path, manifest: Manifest, checkpoint: Path | None) -> tuple[SCNeRF, str]:
    if checkpoint is not None:
        model, _ = load_checkpoint(checkpoint)
        if model.cfg != manifest.config:
            raise BundleError(f"{checkpoint}: its config differs from the bundle's ({bundle})")
        return model.eval(), f"{checkpoint.name} (sha256 {sha256_file(checkpoint)})"
    model = SCNeRF(manifest.config).eval()
    try:
        state = renderer_state_from_current_graph(manifest.graph_path(bundle, "renderer"), model)
    except ReexportError as exc:
        raise BundleError(f"{exc}; pass the bundle's source checkpoint with --checkpoint") from None
    model.renderer.load_state_dict(state)
    return model, "read back from renderer.onnx"


def base_model(bundle: str | Path, checkpoint: str | Path | None = None) -> tuple[SCNeRF, Manifest, dict]:
    """The base bundle's network (its renderer's weights; G1 and G2 stay the bundle's graphs), its
    manifest, and what the refinement record says of where the weights came from."""
    bundle = Path(bundle)
    manifest = Manifest.load(bundle)
    if manifest.precision != FLOAT32:
        raise BundleError(f"{bundle}: a {manifest.precision} bundle; refine its float32 source")
    model, source = _weights(bundle, manifest, Path(checkpoint) if checkpoint else None)
    agreement = renderer_agreement(bundle, manifest, model)
    if not agreement <= AGREEMENT_TOLERANCE:
        raise BundleError(
            f"{bundle}: the renderer's weights ({source}) render {agreement:.3g} away from its renderer.onnx; "
            "pass the bundle's source checkpoint with --checkpoint"
        )
    about = {"base_model_id": manifest.model_id, "base_bundle": bundle.name, "weights": source}
    return model, manifest, {**about, "weights_max_abs_difference": agreement}


def _renderer_graphs(manifest: Manifest) -> tuple[str, ...]:
    return tuple(g for g in RENDERER_GRAPHS if g in manifest.graphs)


def _export_renderers(base: Path, manifest: Manifest, model: SCNeRF, staging: Path) -> tuple[dict, dict]:
    """The renderer graphs of ``model`` written into ``staging``, each checked against PyTorch on
    rays of the base bundle's own features and volumes."""
    encode = bundle_encoder(base, manifest)
    examples = (
        example_inputs(model, encode=encode),
        example_inputs(model, blocks=CHECK_BLOCKS, rays=CHECK_RAYS, encode=encode),
    )
    return export_graphs(model, staging, _renderer_graphs(manifest), examples)


def _copy_unchanged(base: Path, manifest: Manifest, out: Path, names) -> None:
    """The base's graphs ``names`` and licence files into ``out``."""
    for name in names:
        shutil.copyfile(manifest.graph_path(base, name), manifest.graph_path(out, name))
    for licence in base.glob("LICENSE*"):
        shutil.copyfile(licence, out / licence.name)


def write_bundle(
    base: str | Path,
    manifest: Manifest,
    model: SCNeRF | None,
    out: str | Path,
    record: dict,
    staging: Path,
    band: str,
) -> Manifest:
    """The refined bundle in ``out``: the base's encoder and volume graphs, ``model``'s renderer
    graphs (the base's own when ``model`` is None: nothing improved on it), and the manifest with
    ``provenance.refinement = record`` and the band rule ``band``. The graphs are written into
    ``staging`` first and the manifest last, so ``out`` holds a complete bundle except while files
    move."""
    base, out = Path(base), Path(out)
    if staging.exists():
        shutil.rmtree(staging)
    staging.mkdir(parents=True)
    renderers = _renderer_graphs(manifest)
    refined = copy.deepcopy(manifest)
    if model is not None:
        graphs, errors = _export_renderers(base, manifest, model, staging)
        refined.graphs.update(graphs)
        refined.provenance.export_validation_max_abs_error.update(errors)
        refined.provenance.guided_graphs = None  # exported from the refined weights, not read back
    else:
        _copy_unchanged(base, manifest, staging, renderers)
    out.mkdir(parents=True, exist_ok=True)
    _copy_unchanged(base, manifest, out, [g for g in manifest.graphs if g not in renderers])
    for name in renderers:
        os.replace(refined.graph_path(staging, name), refined.graph_path(out, name))
    refined.model_id = refined.expected_model_id()
    refined.provenance.created = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
    refined.provenance.refinement = record
    refined.band = band
    (out / "manifest.json.tmp").write_text(refined.text())
    os.replace(out / "manifest.json.tmp", out / "manifest.json")
    shutil.rmtree(staging)
    return refined
