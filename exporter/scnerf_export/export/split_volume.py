"""`scnerf-export split-volume --bundle IN --out OUT [--volume sweep|slabs]`: a bundle's volume
graphs written again for another way of building the volume (`export.bundle.VOLUME_GRAPHS`), by
default the server's plane sweep (`cost_conv.onnx` + `volume_net.onnx`), without its checkpoint.

A bundle carries no checkpoint, only its graphs. G2's weights are read back from its volume
graphs: the convolutions under their parameter names (``model.volume_net.<conv>.weight``), each
norm's scale and shift as the constants that multiply and then add to that convolution's
normalised output before its leaky ReLU (the first convolution's norm follows the ``conv0`` input
of ``volume_net.onnx`` when the convolution is in a slab graph). The new graphs are exported from
a model with those weights and run side by side with the old ones in ONNX Runtime, at an image
size other than the tracing one and with slabs of several sizes: they are kept only if the volumes
agree (max abs error <= 1e-4). encoder.onnx and renderer.onnx are copied unchanged, so the model
id stays.

`scnerf-export volume-tail --bundle DIR` rewrites a bundle's ``volume_net.onnx`` in place so that
the server computes G2's last step (``export.volume_tail``), as the exporter now writes it; the
volumes are compared the same way before the graph is replaced.
"""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import torch
from onnx import numpy_helper

from .. import __version__
from ..config import ModelConfig
from ..model.network import SCNeRF
from ..rigs import synthetic_rig
from ..runtime.volume_slabs import build_volume, slab_volume_error, volume_build
from . import onnx_graph
from .bundle import (
    CHECK_BLOCKS,
    CHECK_RAYS,
    GRAPHS,
    VOLUME_GRAPHS,
    example_inputs,
    export_graphs,
    graph_entry,
    graph_signatures,
    write_graph,
)
from .manifest import Manifest

AGREEMENT_TOLERANCE = 1e-4
# Why G2 may not be found in a bundle's volume graphs.
_CURRENT_FORM = (
    "graphs in the form this exporter writes (norms as BatchNormalization, transposed convolutions in sub-pixel "
    "form) are not read back: export the bundle from its checkpoint"
)
_CONV_WEIGHT = re.compile(r"^model\.volume_net\.(conv\d+)\.(conv|0)\.weight$")


class SplitVolumeError(ValueError):
    """The bundle's volume graph cannot be split; the message is one line, fit for a CLI."""


def _norm_after(conv_output: str, nodes: list, consumers: dict, constants: dict) -> tuple[np.ndarray, np.ndarray]:
    """Scale and shift of the norm that follows the convolution whose output is ``conv_output``:
    the normalised value ``Sub(conv, mean) * rsqrt(...)`` is multiplied by a constant, then a
    constant is added, then LeakyRelu."""
    for sub in (nodes[k] for k in consumers.get(conv_output, [])):
        if sub.op_type != "Sub" or sub.input[0] != conv_output:
            continue
        for normalised in (nodes[k] for k in consumers.get(sub.output[0], [])):
            scaled = [nodes[k] for k in consumers.get(normalised.output[0], []) if nodes[k].op_type == "Mul"]
            for mul in scaled:
                scale = [constants[n] for n in mul.input if n in constants]
                shifted = [nodes[k] for k in consumers.get(mul.output[0], []) if nodes[k].op_type == "Add"]
                for add in shifted:
                    shift = [constants[n] for n in add.input if n in constants]
                    if len(scale) == 1 and len(shift) == 1:
                        return scale[0].reshape(-1), shift[0].reshape(-1)
    raise SplitVolumeError(f"no norm scale and shift found after {conv_output} ({_CURRENT_FORM})")


def volume_state_from_graphs(paths: list[Path], model: SCNeRF) -> dict[str, torch.Tensor]:
    """G2's parameters (convolutions, norm scales and shifts), read from a bundle's volume graphs."""
    state = dict(model.volume_net.state_dict())  # the norms' running statistics stay unused
    found = {}
    for path in paths:
        proto = onnx.load(str(path))
        nodes = list(proto.graph.node)
        constants = {t.name: numpy_helper.to_array(t) for t in proto.graph.initializer}
        consumers = onnx_graph.consumers(nodes)
        outputs = {o.name for o in proto.graph.output}
        for node in nodes:
            weight = next((m for m in map(_CONV_WEIGHT.match, node.input) if m), None)
            if node.op_type not in ("Conv", "ConvTranspose") or weight is None:
                continue
            conv, kind = weight.groups()
            found[f"{conv}.{kind}.weight"] = constants[weight.group(0)]
            if node.output[0] in outputs:  # a slab graph's first convolution: its norm is in volume_net
                continue
            norm = f"{conv}.bn" if kind == "conv" else f"{conv}.1"
            found[f"{norm}.weight"], found[f"{norm}.bias"] = _norm_after(node.output[0], nodes, consumers, constants)
        if "conv0" in {i.name for i in proto.graph.input}:
            found["conv0.bn.weight"], found["conv0.bn.bias"] = _norm_after("conv0", nodes, consumers, constants)
    for key, param in model.volume_net.named_parameters():
        if key not in found:
            where = ", ".join(map(str, paths))
            raise SplitVolumeError(f"{where}: cannot find G2's parameter {key!r} in the graphs ({_CURRENT_FORM})")
        if tuple(found[key].shape) != tuple(param.shape):
            raise SplitVolumeError(f"{key} has shape {found[key].shape}, the config needs {tuple(param.shape)}")
        state[key] = torch.tensor(found[key])
    return state


def _session(path: Path) -> ort.InferenceSession:
    return ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])


def volumes_agree(
    src: Path, manifest: Manifest, out: Path, volume: str, inputs: dict[str, np.ndarray], slab_sizes=(1, 5, 64)
) -> float:
    """Largest difference between the volume of the bundle ``src`` (``manifest``: its manifest)
    and the one of the new graphs of ``volume`` in ``out`` over slabs of each size in
    ``slab_sizes``, on the volume's ``inputs`` (features, images, projections, depth_planes)."""
    cfg = manifest.config
    graphs = VOLUME_GRAPHS[volume_build(manifest.graphs)]
    old = build_volume({name: _session(manifest.graph_path(src, name)) for name in graphs}, inputs, cfg)
    return slab_volume_error(old, out, volume, inputs, cfg, slab_sizes)


def check_inputs(encoder: Path, cfg: ModelConfig) -> dict[str, np.ndarray]:
    """The volume's inputs for a synthetic rig at the check size (not the tracing one), with the
    features of the bundle's own encoder graph."""
    rig = {k: v.numpy() for k, v in synthetic_rig(cfg, 32 * CHECK_BLOCKS[0], 32 * CHECK_BLOCKS[1], seed=1).items()}
    (features,) = _session(encoder).run(None, {"images": rig["images"]})
    return {"features": features, **{k: rig[k] for k in ("images", "projections", "depth_planes")}}


def split_volume_bundle(
    bundle_dir: str | Path, out_dir: str | Path, volume: str = "sweep", model: SCNeRF | None = None
) -> Manifest:
    """The bundle ``bundle_dir`` with its volume graphs written again as ``volume`` into ``out_dir``.
    G2 is ``model``'s (the network the bundle was exported from, its config the manifest's) or,
    without it, read back from the bundle's volume graphs."""
    src, out = Path(bundle_dir), Path(out_dir)
    if src.resolve() == out.resolve():
        raise SplitVolumeError("--out must differ from --bundle")
    if volume not in ("slabs", "sweep"):
        raise SplitVolumeError(f"--volume {volume!r}: slabs or sweep")
    manifest = Manifest.load(src)
    old_build = volume_build(manifest.graphs)
    if old_build == volume:
        raise SplitVolumeError(f"{src}: its volume graphs already build the volume as {volume!r}")
    cfg = manifest.config
    if cfg.norm_statistics != "batch":
        raise SplitVolumeError(f"{src}: norm_statistics {cfg.norm_statistics!r}; re-export it from its checkpoint")
    read_back = model is None
    if read_back:
        model = SCNeRF(cfg).eval()
        old_graphs = [manifest.graph_path(src, name) for name in VOLUME_GRAPHS[old_build]]
        model.volume_net.load_state_dict(volume_state_from_graphs(old_graphs, model))
    elif model.cfg != cfg:
        raise SplitVolumeError(f"{src}: the model's config is not the bundle's")
    model = model.eval()
    # The encoder's weights are not read back: the volume graphs' inputs come from the bundle's own
    # encoder graph, the example features only need plausible values.
    out.mkdir(parents=True, exist_ok=True)
    examples = (example_inputs(model), example_inputs(model, blocks=CHECK_BLOCKS, rays=CHECK_RAYS))
    graphs, errors = export_graphs(model, out, VOLUME_GRAPHS[volume], examples)
    inputs = check_inputs(manifest.graph_path(src, "encoder"), cfg)
    agreement = volumes_agree(src, manifest, out, volume, inputs)
    if not agreement <= AGREEMENT_TOLERANCE:
        for name in VOLUME_GRAPHS[volume]:
            (out / graphs[name].file).unlink()
        raise SplitVolumeError(f"{src}: the new graphs' volume differs from the bundle's by {agreement:.3g}")
    volume_graphs = {name for names in VOLUME_GRAPHS.values() for name in names}
    kept = {k: entry for k, entry in manifest.graphs.items() if k not in volume_graphs}
    for entry in kept.values():
        shutil.copyfile(src / entry.file, out / entry.file)
    for extra in src.iterdir():
        if extra.name.startswith("LICENSE"):
            shutil.copyfile(extra, out / extra.name)
    manifest.graphs = {k: kept.get(k) or graphs[k] for k in GRAPHS[volume] if k in kept or k in graphs}
    manifest.model_id = manifest.expected_model_id()
    manifest.provenance.volume_split = {
        "exporter_version": __version__,
        "volume_max_abs_difference": agreement,
        "export_validation_max_abs_error": errors,
        "what": f"{' and '.join(f'{g}.onnx' for g in VOLUME_GRAPHS[old_build])} written again as "
        f"{' and '.join(f'{g}.onnx' for g in VOLUME_GRAPHS[volume])} from "
        f"{'the weights in the source volume graphs' if read_back else 'the model the bundle was exported from'} "
        f"(the volume built as {volume!r}); {' and '.join(f'{k}.onnx' for k in kept)} unchanged",
    }
    manifest.save(out)
    return manifest


def leave_volume_tail_to_server(bundle_dir: str | Path) -> float:
    """Rewrites the bundle's ``volume_net.onnx`` in place without G2's last step (the server's,
    ``tail_in_server``), updates its manifest entry and provenance; returns the largest difference
    between the volumes before and after. The model id stays (the renderer is unchanged)."""
    bundle = Path(bundle_dir)
    manifest = Manifest.load(bundle)
    cfg = manifest.config
    entry = manifest.graphs.get("volume_net")
    if entry is None:
        raise SplitVolumeError(f"{bundle}: no volume_net.onnx (scnerf-export split-volume writes one)")
    if "volume" not in {t.name for t in entry.outputs}:
        raise SplitVolumeError(f"{bundle}: volume_net.onnx already leaves G2's last step to the server")
    path = manifest.graph_path(bundle, "volume_net")
    model = SCNeRF(cfg)
    rewritten = path.with_name("volume_net.rewritten.onnx")
    write_graph(onnx.load(str(path)), model, "volume_net", rewritten)
    inputs = check_inputs(manifest.graph_path(bundle, "encoder"), cfg)
    build = volume_build(manifest.graphs)
    slab = {name: _session(manifest.graph_path(bundle, name)) for name in VOLUME_GRAPHS[build] if name != "volume_net"}
    before = build_volume({**slab, "volume_net": _session(path)}, inputs, cfg)
    after = build_volume({**slab, "volume_net": _session(rewritten)}, inputs, cfg)
    difference = float(np.abs(after - before).max())
    if not difference <= AGREEMENT_TOLERANCE:
        rewritten.unlink()
        raise SplitVolumeError(f"{bundle}: the rewritten volume_net's volume differs by {difference:.3g}")
    rewritten.replace(path)
    manifest.graphs["volume_net"] = graph_entry(path, graph_signatures(model)["volume_net"])
    manifest.model_id = manifest.expected_model_id()
    manifest.provenance.extra["volume_tail"] = {
        "exporter_version": __version__,
        "volume_max_abs_difference": difference,
        "what": "volume_net.onnx written again without G2's last step, which the server computes",
    }
    manifest.save(bundle)
    return difference
