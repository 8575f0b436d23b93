"""`scnerf-export split-volume --bundle IN --out OUT`: a bundle's `volume.onnx` as the two graphs
that build the volume slab by slab, without its checkpoint.

A bundle carries no checkpoint, only its graphs. G2's weights are read back from the volume graph:
the convolutions under their parameter names (``model.volume_net.<conv>.weight``), each norm's
scale and shift as the constants that multiply and then add to that convolution's normalised
output before its leaky ReLU. The two graphs are exported from a model with those weights and run
side by side with the old graph in ONNX Runtime, at an image size other than the tracing one and
with slabs of several sizes: they are kept only if the volumes agree (max abs error <= 1e-4).
encoder.onnx and renderer.onnx are copied unchanged, so the model id stays.
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
from ..runtime.volume_slabs import slab_volume_error
from . import onnx_graph
from .bundle import CHECK_BLOCKS, CHECK_RAYS, VOLUME_GRAPHS, example_inputs, export_graphs
from .manifest import read_manifest, write_manifest

AGREEMENT_TOLERANCE = 1e-4
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
    raise SplitVolumeError(f"no norm scale and shift found after {conv_output}")


def volume_state_from_graph(path: Path, model: SCNeRF) -> dict[str, torch.Tensor]:
    """G2's parameters (convolutions, norm scales and shifts), read from a volume.onnx."""
    proto = onnx.load(str(path))
    nodes = list(proto.graph.node)
    constants = {t.name: numpy_helper.to_array(t) for t in proto.graph.initializer}
    consumers = onnx_graph.consumers(nodes)
    state = dict(model.volume_net.state_dict())  # the norms' running statistics stay unused
    found = {}
    for node in nodes:
        weight = next((m for m in map(_CONV_WEIGHT.match, node.input) if m), None)
        if node.op_type not in ("Conv", "ConvTranspose") or weight is None:
            continue
        conv, kind = weight.groups()
        norm = f"{conv}.bn" if kind == "conv" else f"{conv}.1"
        scale, shift = _norm_after(node.output[0], nodes, consumers, constants)
        found[f"{conv}.{kind}.weight"] = constants[weight.group(0)]
        found[f"{norm}.weight"], found[f"{norm}.bias"] = scale, shift
    for key, param in model.volume_net.named_parameters():
        if key not in found:
            raise SplitVolumeError(f"{path}: cannot find G2's parameter {key!r} in the graph")
        if tuple(found[key].shape) != tuple(param.shape):
            raise SplitVolumeError(f"{path}: {key} has shape {found[key].shape}, the config needs {tuple(param.shape)}")
        state[key] = torch.tensor(found[key])
    return state


def _session(path: Path) -> ort.InferenceSession:
    return ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])


def volumes_agree(old_volume: Path, out: Path, inputs: dict[str, np.ndarray], slab_sizes=(1, 5, 64)) -> float:
    """Largest difference between the old graph's volume and the new graphs' over slabs of each
    size in ``slab_sizes``, on the volume's ``inputs`` (features, images, projections,
    depth_planes)."""
    (old,) = _session(old_volume).run(None, inputs)
    return slab_volume_error(old, out, inputs, slab_sizes)


def check_inputs(encoder: Path, cfg: ModelConfig) -> dict[str, np.ndarray]:
    """The volume's inputs for a synthetic rig at the check size (not the tracing one), with the
    features of the bundle's own encoder graph."""
    rig = {k: v.numpy() for k, v in synthetic_rig(cfg, 32 * CHECK_BLOCKS[0], 32 * CHECK_BLOCKS[1], seed=1).items()}
    (features,) = _session(encoder).run(None, {"images": rig["images"]})
    return {"features": features, **{k: rig[k] for k in ("images", "projections", "depth_planes")}}


def split_volume_bundle(bundle_dir: str | Path, out_dir: str | Path) -> dict:
    src, out = Path(bundle_dir), Path(out_dir)
    if src.resolve() == out.resolve():
        raise SplitVolumeError("--out must differ from --bundle")
    manifest = read_manifest(src)
    if "volume" not in manifest["graphs"]:
        raise SplitVolumeError(f"{src}: no volume graph (already split?)")
    cfg = ModelConfig.from_dict(manifest["config"])
    if cfg.norm_statistics != "batch":
        raise SplitVolumeError(f"{src}: norm_statistics {cfg.norm_statistics!r}; re-export it from its checkpoint")
    model = SCNeRF(cfg).eval()
    old_volume = src / manifest["graphs"]["volume"]["file"]
    model.volume_net.load_state_dict(volume_state_from_graph(old_volume, model))
    # The encoder's weights are not read back: the volume graphs' inputs come from the bundle's own
    # encoder graph, the example features only need plausible values.
    out.mkdir(parents=True, exist_ok=True)
    examples = (example_inputs(model), example_inputs(model, blocks=CHECK_BLOCKS, rays=CHECK_RAYS))
    graphs, errors = export_graphs(model, out, VOLUME_GRAPHS, examples)
    agreement = volumes_agree(old_volume, out, check_inputs(src / manifest["graphs"]["encoder"]["file"], cfg))
    if not agreement <= AGREEMENT_TOLERANCE:
        for name in VOLUME_GRAPHS:
            (out / graphs[name]["file"]).unlink()
        raise SplitVolumeError(f"{src}: the slab graphs' volume differs from the bundle's by {agreement:.3g}")
    for name in ("encoder", "renderer"):
        shutil.copyfile(src / manifest["graphs"][name]["file"], out / manifest["graphs"][name]["file"])
    for extra in src.iterdir():
        if extra.name.startswith("LICENSE"):
            shutil.copyfile(extra, out / extra.name)
    del manifest["graphs"]["volume"]
    manifest["graphs"] = {k: manifest["graphs"].get(k) or graphs[k] for k in ("encoder", *VOLUME_GRAPHS, "renderer")}
    manifest["provenance"]["volume_split"] = {
        "exporter_version": __version__,
        "volume_max_abs_difference": agreement,
        "export_validation_max_abs_error": errors,
        "what": "volume.onnx written again as cost_slab.onnx and volume_net.onnx (the volume built slab by slab) "
        "from the weights in the source volume graph; encoder.onnx and renderer.onnx unchanged",
    }
    write_manifest(out, manifest)
    return manifest
