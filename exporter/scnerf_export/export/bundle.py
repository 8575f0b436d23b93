"""ONNX sub-graphs + manifest.json: the bundle the server runs (docs/bundle.md)."""

from __future__ import annotations

import datetime as _dt
import warnings
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import torch
from torch import nn
from torch.export import Dim

from .. import __version__
from ..config import ModelConfig
from ..model.checkpoint import sha256_file
from ..model.cost_volume import build_cost_volume, slab_halo
from ..model.network import SCNeRF
from ..model.renderer import nearest_heads
from ..rigs import synthetic_rig
from ..runtime.volume_slabs import slab_volume_error, volume_from_tail
from .external_data import check_holds_its_weights
from .manifest import FORMAT_VERSION, GraphEntry, GuidedPolicy, Manifest, Provenance, model_id, tensor_specs
from .ray_groups import attention_cores_in_ray_groups
from .subpixel_interleave import interleaves_as_depth_to_space
from .volume_tail import tail_in_server

OPSET = 20

# Example sizes for tracing: small and unlike any other axis so that no dimension is specialised.
_EXAMPLE_BLOCKS_H, _EXAMPLE_BLOCKS_W, _EXAMPLE_RAYS = 2, 3, 37
# A second validation size, not the tracing one: a size frozen into a graph shows up only there.
CHECK_BLOCKS, CHECK_RAYS = (3, 2), 512


class EncoderGraph(nn.Module):
    def __init__(self, model: SCNeRF):
        super().__init__()
        self.model = model

    def forward(self, images):
        return self.model.encode(images)


class VolumeGraph(nn.Module):
    def __init__(self, model: SCNeRF):
        super().__init__()
        self.model = model

    def forward(self, features, images, projections, depth_planes):
        return self.model.build_volume(features, images, projections, depth_planes)


class CostSlabGraph(nn.Module):
    """The cost volume of a slab of planes and G2's first convolution over it."""

    def __init__(self, model: SCNeRF):
        super().__init__()
        self.model = model

    def forward(self, features, images, projections, depth_planes, plane_inside):
        return self.model.volume_slab(features, images, projections, depth_planes, plane_inside)


class CostConvGraph(nn.Module):
    """G2's first convolution over a slab of the cost volume that the server computes (its plane
    sweep, ``runtime.plane_sweep``)."""

    def __init__(self, model: SCNeRF):
        super().__init__()
        self.model = model

    def forward(self, cost):
        return self.model.volume_net.first_conv_of_slab(cost)


class VolumeNetGraph(nn.Module):
    """G2 from its first convolution over the whole volume (the slabs' outputs, concatenated)."""

    def __init__(self, model: SCNeRF):
        super().__init__()
        self.model = model

    def forward(self, conv0):
        return self.model.volume_from_slabs(conv0)


# The graphs that build the volume, by way of building it: as one graph (the cost volume and G2 in
# one run), or slab by slab of depth planes in a fraction of the memory, the cost volume of each
# slab computed by the graph ("slabs") or by the server's plane sweep ("sweep", the fastest).
# `scnerf-export split-volume` turns one into another.
VOLUME_GRAPHS = {"whole": ("volume",), "slabs": ("cost_slab", "volume_net"), "sweep": ("cost_conv", "volume_net")}
# Guided sampling's two renderers (runtime/guided.py): the renderer that also returns what guides
# the other rays, and the renderer at K given samples per ray.
GUIDED_GRAPHS = ("renderer_guide", "renderer_fine")
GRAPHS = {build: ("encoder", *graphs, "renderer", *GUIDED_GRAPHS) for build, graphs in VOLUME_GRAPHS.items()}


def renderer_input_names(model: SCNeRF) -> list[str]:
    """Inputs the renderer of this variant reads (docs/bundle.md): unused ones are not declared."""
    cfg = model.cfg
    names = ["ray_origins", "ray_directions", "near_far"]
    if cfg.variant != "mvsnerf":
        names.append("depth_range")
    names += ["volume", "images"]
    if cfg.appearance_rectification:
        names.append("features")
    return names + ["intrinsics", "extrinsics"]


class RendererGraph(nn.Module):
    def __init__(self, model: SCNeRF):
        super().__init__()
        self.model = model
        self.names = renderer_input_names(model)

    def forward(self, *args):
        given = dict(zip(self.names, args))
        return self.model.renderer(
            given["ray_origins"],
            given["ray_directions"],
            given["near_far"],
            given.get("depth_range", given["near_far"]),
            given["volume"],
            given["images"],
            given.get("features"),
            given["intrinsics"],
            given["extrinsics"],
        )


def guided_input_names(model: SCNeRF, graph: str) -> list[str]:
    """Inputs of ``renderer_guide`` (the renderer's) and ``renderer_fine`` (the renderer's with
    the rays' samples, then each rectifier's heads of the guide rays and each ray's guide ray)."""
    names = renderer_input_names(model)
    if graph == "renderer_guide":
        return names
    rectifiers = list(model.renderer.rectifiers())
    taps = ["head_index"] if rectifiers else []
    return names[:2] + ["sample_index", "sample_multiplicity"] + names[2:] + [f"{r}_heads" for r in rectifiers] + taps


def _renderer_call(names: list[str], args: tuple) -> dict[str, torch.Tensor]:
    """A renderer graph's positional inputs by name, with the defaults of undeclared ones."""
    given = dict(zip(names, args))
    given.setdefault("depth_range", given["near_far"])
    given.setdefault("features", None)
    return given


class GuideGraph(nn.Module):
    """The renderer at the S uniform samples, with each ray's weights and rectifier heads."""

    def __init__(self, model: SCNeRF):
        super().__init__()
        self.model = model
        self.names = guided_input_names(model, "renderer_guide")

    def forward(self, *args):
        g = _renderer_call(self.names, args)
        shading = self.model.renderer.guide(
            *(g[n] for n in ("ray_origins", "ray_directions", "near_far", "depth_range", "volume", "images")),
            g["features"],
            g["intrinsics"],
            g["extrinsics"],
        )
        return (shading.rgb, shading.depth, shading.opacity, shading.weights, *shading.heads.values())


class FineGraph(nn.Module):
    """The renderer at K given samples per ray, with the heads of the nearest guide ray."""

    def __init__(self, model: SCNeRF):
        super().__init__()
        self.model = model
        self.names = guided_input_names(model, "renderer_fine")

    def forward(self, *args):
        g = _renderer_call(self.names, args)
        heads = {name: nearest_heads(g[f"{name}_heads"], g["head_index"]) for name in self.model.renderer.rectifiers()}
        shading = self.model.renderer.render_samples(
            *(g[n] for n in ("ray_origins", "ray_directions", "sample_index", "sample_multiplicity", "near_far")),
            g["depth_range"],
            g["volume"],
            g["images"],
            g["features"],
            g["intrinsics"],
            g["extrinsics"],
            heads,
        )
        return shading.rgb, shading.depth, shading.opacity, shading.weights


# The rectifiers of the paper's variant, in the order they run (``Renderer.rectifiers``).
RECTIFIERS = ("geometry", "appearance")
# volume_net.onnx's outputs as the exporter writes it: G2's last step left to the server.
VOLUME_NET_OUTPUTS = ("phases", "skip_affine", "phases_affine")


def graph_contract(cfg: ModelConfig) -> dict[str, dict[str, list[dict]]]:
    """The graphs' I/O contract of docs/bundle.md for the hyper-parameters ``cfg``: per graph, its
    inputs and outputs in manifest order, each with its shape (fixed sizes, named dynamic axes) and
    whether every bundle's graph declares it. The server checks manifests against the same
    contract (server/src/bundle/contract.rs); tests/fixtures/rules/graph_contract.json holds
    both to it. Optional tensors: the inputs a variant does not read, the rectifiers' heads, and
    ``volume_net``'s outputs, in one of its two forms (the volume, or what the server computes
    it from: the form the exporter writes)."""
    v, c, d = cfg.views, cfg.feature_channels, cfg.depth_planes
    cv = cfg.volume_channels
    images, features = [v, 3, "H", "W"], [v, c, "h", "w"]
    vol = [1, cv, d, "Hp", "Wp"]
    slab_conv0 = [1, cv, "Ds", "Hp", "Wp"]
    heads = cfg.heads * cfg.head_dim

    def t(name: str, shape: list, required: bool = True) -> dict:
        return {"name": name, "required": required, "shape": shape}

    def sources(planes) -> list[dict]:
        return [t("features", features), t("images", images), t("projections", [v, 4, 4]), t("depth_planes", [planes])]

    rays = [t("ray_origins", ["R", 3]), t("ray_directions", ["R", 3])]
    scene = [
        t("near_far", [2]),
        t("depth_range", [2], required=False),
        t("volume", vol),
        t("images", images),
        t("features", features, required=False),
        t("intrinsics", [v, 3, 3]),
        t("extrinsics", [v, 4, 4]),
    ]
    pixels = [t("rgb", ["R", 3]), t("depth", ["R"]), t("opacity", ["R"])]
    rectifier_heads = [t(f"{r}_heads", ["G", heads, cfg.width], required=False) for r in RECTIFIERS]
    return {
        "encoder": {"inputs": [t("images", images)], "outputs": [t("features", features)]},
        "volume": {"inputs": sources(d), "outputs": [t("volume", vol)]},
        "cost_slab": {"inputs": [*sources("Dh"), t("plane_inside", ["Dh"])], "outputs": [t("conv0", slab_conv0)]},
        "cost_conv": {
            "inputs": [t("cost", [1, 3 * v + c, "Dh", "Hp", "Wp"])],
            "outputs": [t("conv0", slab_conv0)],
        },
        "volume_net": {
            "inputs": [t("conv0", vol)],
            "outputs": [
                t("volume", vol, required=False),
                t("phases", [1, 8 * cv, d // 2, "Hp/2", "Wp/2"], required=False),
                t("skip_affine", [2, cv], required=False),
                t("phases_affine", [2, cv], required=False),
            ],
        },
        "renderer": {"inputs": rays + scene, "outputs": pixels},
        "renderer_guide": {
            "inputs": rays + scene,
            "outputs": [*pixels, t("sample_weights", ["R", cfg.samples])]
            + [{**h, "shape": ["R", *h["shape"][1:]]} for h in rectifier_heads],
        },
        "renderer_fine": {
            "inputs": [*rays, t("sample_index", ["R", "K"]), t("sample_multiplicity", ["R", "K"]), *scene]
            + [*rectifier_heads, t("head_index", ["R"], required=False)],
            "outputs": [*pixels, t("sample_weights", ["R", "K"])],
        },
    }


def graph_signatures(model: SCNeRF) -> dict[str, dict[str, dict[str, list]]]:
    """Names and shapes of every graph's inputs and outputs, as written in the manifest: the
    contract's tensors this model's graphs declare (those of its variant; ``volume_net`` in the form
    the exporter writes), in the contract's order."""
    rectifiers = list(model.renderer.rectifiers())
    renderer = renderer_input_names(model)
    guide_outputs = ["rgb", "depth", "opacity", "sample_weights", *(f"{r}_heads" for r in rectifiers)]
    declared = {
        ("volume_net", "outputs"): VOLUME_NET_OUTPUTS,
        ("renderer", "inputs"): renderer,
        ("renderer_guide", "inputs"): renderer,
        ("renderer_guide", "outputs"): guide_outputs,
        ("renderer_fine", "inputs"): guided_input_names(model, "renderer_fine"),
    }
    signatures = {}
    for graph, sides in graph_contract(model.cfg).items():
        signatures[graph] = {}
        for side, tensors in sides.items():
            names = declared.get((graph, side))
            signatures[graph][side] = {
                tensor["name"]: tensor["shape"] for tensor in tensors if names is None or tensor["name"] in names
            }
    return signatures


def example_inputs(
    model: SCNeRF,
    seed: int = 0,
    blocks: tuple[int, int] = (_EXAMPLE_BLOCKS_H, _EXAMPLE_BLOCKS_W),
    rays: int = _EXAMPLE_RAYS,
    encode=None,
) -> dict[str, dict[str, torch.Tensor]]:
    """Plausible tensors for tracing and validation: a small scene with real camera geometry,
    images of ``blocks`` x 32 pixels, ``rays`` target rays. ``encode`` (images, projections,
    depth planes) -> (features, volume) stands in for the model's own G1 and G2 (a bundle's graphs,
    when only the renderer's weights are known)."""
    cfg = model.cfg
    rig = synthetic_rig(cfg, 32 * blocks[0], 32 * blocks[1], seed=seed)
    d = cfg.depth_planes
    # The first slab, with its halo plane outside the volume (and a size of its own, 5 planes).
    index, inside = slab_halo(d, 0, min(5, d))
    with torch.no_grad():
        features = model.encode(rig["images"])
        cost = build_cost_volume(features, rig["images"], rig["projections"], rig["depth_planes"], cfg.pad)
        volume = model.volume_net(cost)  # = model.build_volume(...)
        conv0 = model.volume_net.conv0.conv(cost)
        halo = torch.from_numpy(index)
        slab_cost = build_cost_volume(features, rig["images"], rig["projections"], rig["depth_planes"][halo], cfg.pad)
        slab_cost = slab_cost * torch.from_numpy(inside).view(1, 1, -1, 1, 1)
    if encode is not None:
        features, volume = encode(rig["images"], rig["projections"], rig["depth_planes"])
    rays = {
        "ray_origins": rig["ray_origins"][:rays],
        "ray_directions": rig["ray_directions"][:rays],
        # A tensor of its own: torch.export would alias two inputs given the same tensor object.
        "near_far": rig["near_far"],
        "depth_range": rig["near_far"] * torch.tensor([1.05, 0.95]),
        "volume": volume,
        "images": rig["images"],
        "features": features,
        "intrinsics": rig["intrinsics"],
        "extrinsics": rig["extrinsics"],
    }
    guide = {n: rays[n] for n in renderer_input_names(model)}
    fine = guided_examples(model, rays)
    return {
        "encoder": {"images": rig["images"]},
        "volume": {
            "features": features,
            "images": rig["images"],
            "projections": rig["projections"],
            "depth_planes": rig["depth_planes"],
        },
        "cost_slab": {
            "features": features,
            "images": rig["images"],
            "projections": rig["projections"],
            "depth_planes": rig["depth_planes"][torch.from_numpy(index)],
            "plane_inside": torch.from_numpy(inside),
        },
        "cost_conv": {"cost": slab_cost},
        "volume_net": {"conv0": conv0},
        "renderer": {n: rays[n] for n in renderer_input_names(model)},
        "renderer_guide": guide,
        "renderer_fine": {n: fine[n] for n in guided_input_names(model, "renderer_fine")},
    }


def guided_examples(model: SCNeRF, rays: dict[str, torch.Tensor], count: int = 5, grid: int = 7) -> dict:
    """The fine graph's inputs for the example rays: ``count`` increasing samples of each ray with
    multiplicities 1-3, and heads grids from the guide pass of ``grid`` of the rays, each ray
    reading a random one (sizes unlike any other axis, so none is specialised)."""
    cfg = model.cfg
    n = rays["ray_origins"].shape[0]
    rng = torch.Generator().manual_seed(7)
    index = torch.stack([torch.randperm(cfg.samples, generator=rng)[:count].sort().values for _ in range(n)])
    guide_rays = {k: (v[:grid] if k.startswith("ray_") else v) for k, v in rays.items()}
    args = _renderer_call(renderer_input_names(model), tuple(guide_rays[k] for k in renderer_input_names(model)))
    with torch.no_grad():
        shading = model.renderer.guide(
            *(args[k] for k in ("ray_origins", "ray_directions", "near_far", "depth_range", "volume", "images")),
            args["features"],
            args["intrinsics"],
            args["extrinsics"],
        )
    return {
        **rays,
        "sample_index": index.float(),
        "sample_multiplicity": torch.randint(1, 4, (n, count), generator=rng).float(),
        **{f"{name}_heads": h for name, h in shading.heads.items()},
        "head_index": torch.randint(0, grid, (n,), generator=rng).float(),
    }


def _dynamic_shapes(model: SCNeRF, graph: str) -> dict:
    pad = model.cfg.pad
    hb, wb, rays = Dim("hb", min=1, max=512), Dim("wb", min=1, max=512), Dim("R", min=1)
    spatial = {
        "Dh": Dim("Dh", min=3, max=model.cfg.depth_planes + 2),
        "H": 32 * hb,
        "W": 32 * wb,
        "h": 8 * hb,
        "w": 8 * wb,
        "Hp": 8 * hb + 2 * pad,
        "Wp": 8 * wb + 2 * pad,
        "R": rays,
        "K": Dim("K", min=1, max=model.cfg.samples),
        "G": Dim("G", min=1),
    }
    shapes = graph_signatures(model)[graph]["inputs"]
    return {name: {i: spatial[a] for i, a in enumerate(shape) if isinstance(a, str)} for name, shape in shapes.items()}


def rename_dims(proto: onnx.ModelProto, signature: dict) -> None:
    """Give dynamic axes the manifest's names (the exporter invents its own)."""
    for values, specs in ((proto.graph.input, signature["inputs"]), (proto.graph.output, signature["outputs"])):
        for value in values:
            for dim, axis in zip(value.type.tensor_type.shape.dim, specs[value.name]):
                if isinstance(axis, str):
                    dim.ClearField("dim_value")
                    dim.dim_param = axis


def _strip_debug_metadata(proto: onnx.ModelProto) -> None:
    """Drop the exporter's per-node debug records (Python stack traces and object addresses):
    without them the same model exports to the same bytes, so a bundle's model id is reproducible."""
    del proto.graph.metadata_props[:]
    for node in proto.graph.node:
        del node.metadata_props[:]
        node.doc_string = ""


def export_graph(module: nn.Module, inputs: dict[str, torch.Tensor], model: SCNeRF, graph: str, path: Path) -> None:
    write_graph(traced_graph(module, inputs, model, graph), model, graph, path)


def write_graph(proto: onnx.ModelProto, model: SCNeRF, graph: str, path: Path) -> None:
    """Writes ``graph`` as torch exported it (``traced_graph``) in the form a bundle holds:
    ``volume_net`` without G2's last step, the dynamic axes under the manifest's names, checked."""
    if graph == "volume_net":
        tail_in_server(proto, model.cfg.activation_slope)
    rename_dims(proto, graph_signatures(model)[graph])
    onnx.checker.check_model(proto, full_check=True)
    onnx.save(proto, path)


def traced_graph(module: nn.Module, inputs: dict[str, torch.Tensor], model: SCNeRF, graph: str) -> onnx.ModelProto:
    """The graph as torch exports it, with the rewrites that keep what it computes and only
    change how ONNX Runtime runs it."""
    signature = graph_signatures(model)[graph]
    dynamic = tuple(_dynamic_shapes(model, graph).values())
    if isinstance(module, (RendererGraph, GuideGraph, FineGraph)):  # forward(*args): one tuple argument
        dynamic = (dynamic,)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        program = torch.onnx.export(
            module,
            tuple(inputs.values()),
            dynamo=True,
            opset_version=OPSET,
            input_names=list(inputs),
            output_names=list(_traced_outputs(graph, signature)),
            dynamic_shapes=dynamic,
            optimize=True,
            verbose=False,
        )
    proto = program.model_proto
    _strip_debug_metadata(proto)
    if graph in ("renderer", "renderer_guide"):
        attention_cores_in_ray_groups(proto)
    if graph in ("volume", "volume_net"):
        interleaves_as_depth_to_space(proto)
    return proto


def _traced_outputs(graph: str, signature: dict) -> list[str]:
    """The outputs of the graph torch writes: ``volume_net``'s module returns the volume, whose last
    step ``tail_in_server`` then leaves to the server."""
    return ["volume"] if graph == "volume_net" else list(signature["outputs"])


def graph_entry(path: Path, signature: dict[str, dict[str, list]]) -> GraphEntry:
    """The manifest's entry of the graph written at ``path`` (in the bundle's folder) with
    ``signature`` (one of ``graph_signatures``)."""
    check_holds_its_weights(path)
    return GraphEntry(
        path.name, sha256_file(path), tensor_specs(signature["inputs"]), tensor_specs(signature["outputs"])
    )


# A graph agrees with PyTorch when its largest difference is within `tolerance` (absolute) or
# within this share of the output's scale (its largest magnitude), whichever is larger: float32
# sums taken in another order differ in proportion to the values summed. Measured on the public
# MVSNeRF weights (`python -m bench.export_spread`, docs/results.md "Export tolerances"): at most
# 4.6e-6 of the scale (cost_slab: 1.06e-3 on outputs of magnitude 330), the same at 1, 2 and 4
# ONNX Runtime threads and 1 and 2 torch threads; 2e-5 leaves 4x room for other CPUs.
RELATIVE_TOLERANCE = 2e-5


class GraphMismatch(ValueError):
    """A written graph that does not compute what the PyTorch model does; one line, for the CLI."""


def allowed_error(tolerance: float, outputs) -> float:
    """``tolerance``, or ``RELATIVE_TOLERANCE`` of the outputs' scale when that is larger."""
    scale = max(float(np.abs(np.asarray(o)).max(initial=0.0)) for o in outputs)
    return max(tolerance, RELATIVE_TOLERANCE * scale)


def mismatch(what: str, error: float, allowed: float) -> GraphMismatch:
    return GraphMismatch(
        f"{what} differs from PyTorch's by {error:.3g}, more than the {allowed:.3g} allowed "
        f"(the larger of an absolute bound and {RELATIVE_TOLERANCE:g} of the output's scale): the exported graph "
        "does not compute what the model does on this machine; nothing was written to the manifest"
    )


def validate_graph(path: Path, module: nn.Module, inputs: dict[str, torch.Tensor], tolerance: float) -> float:
    """Run the written graph in ONNX Runtime on the tracing inputs; return max abs error vs torch,
    refused beyond ``allowed_error``. ``volume_net``'s volume is the one the server computes from
    the graph's outputs."""
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    feeds = {k: v.numpy() for k, v in inputs.items()}
    got = session.run(None, feeds)
    if isinstance(module, VolumeNetGraph):
        parts = dict(zip([o.name for o in session.get_outputs()], got))
        got = [volume_from_tail(feeds["conv0"], parts, module.model.cfg.activation_slope)]
    with torch.no_grad():
        want = module(*inputs.values())
    want = [w.numpy() for w in (want if isinstance(want, (tuple, list)) else (want,))]
    error = max(float(np.abs(g - w).max()) for g, w in zip(got, want))
    allowed = allowed_error(tolerance, want)
    if not error <= allowed:
        raise mismatch(f"{path.name}: ONNX Runtime's output", error, allowed)
    return error


def validate_slab_volume(
    model: SCNeRF, out: Path, build: str, inputs: dict[str, torch.Tensor], tolerance: float
) -> float:
    """The slab graphs' volume (``build``: "slabs" or "sweep"), over slabs of several sizes,
    against PyTorch's whole volume: each graph agreeing with its own module does not show that the
    slabs add up to the volume."""
    with torch.no_grad():
        want = model.build_volume(*inputs.values()).numpy()
    error = slab_volume_error(want, out, build, {k: v.numpy() for k, v in inputs.items()}, model.cfg)
    allowed = allowed_error(tolerance, [want])
    if not error <= allowed:
        raise mismatch("the slab graphs' volume", error, allowed)
    return error


def export_bundle(
    model: SCNeRF, out_dir: str | Path, provenance: dict, volume: str = "whole", created: str | None = None
) -> Manifest:
    """Write the graphs (``volume``: the way they build the volume, a key of VOLUME_GRAPHS) and
    manifest.json into out_dir and validate them. ``provenance``: what the checkpoint loader says
    of the weights (source, training, licence); ``created``: the manifest's time of creation, now
    unless given (the committed test fixtures fix it, so that they can be written again unchanged)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    model = model.eval()
    inputs = example_inputs(model)
    checks = example_inputs(model, blocks=CHECK_BLOCKS, rays=CHECK_RAYS)
    graphs, errors = export_graphs(model, out, GRAPHS[volume], (inputs, checks))
    if volume != "whole":
        validate_slab_volume(model, out, volume, checks["volume"], tolerance=1e-4)
    export = {
        "exporter_version": __version__,
        "torch_version": torch.__version__,
        "opset": OPSET,
        "created": created or _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "export_validation_max_abs_error": errors,
        "metrics": None,
        "source_checkpoint": None,
        "source_sha256": None,
    }
    manifest = Manifest(
        format_version=FORMAT_VERSION,
        model_id=model_id(model.cfg.variant, {name: entry.sha256 for name, entry in graphs.items()}),
        variant=model.cfg.variant,
        config=model.cfg,
        graphs=graphs,
        provenance=Provenance.from_json({**export, **write_licences(out, provenance)}),
        guided=GuidedPolicy.for_model(model.cfg),
    )
    manifest.save(out)
    return manifest


def graph_modules(model: SCNeRF) -> dict[str, nn.Module]:
    return {
        "encoder": EncoderGraph(model),
        "volume": VolumeGraph(model),
        "cost_slab": CostSlabGraph(model),
        "cost_conv": CostConvGraph(model),
        "volume_net": VolumeNetGraph(model),
        "renderer": RendererGraph(model),
        "renderer_guide": GuideGraph(model),
        "renderer_fine": FineGraph(model),
    }


def export_graphs(
    model: SCNeRF, out: Path, names: tuple[str, ...], examples: tuple[dict, ...]
) -> tuple[dict[str, GraphEntry], dict[str, float]]:
    """Writes the graphs ``names`` of ``model`` into ``out``, each checked against PyTorch on every
    example's inputs (traced on the first); their manifest entries and largest errors."""
    modules, signatures = graph_modules(model), graph_signatures(model)
    graphs, errors = {}, {}
    for name in names:
        path = out / f"{name}.onnx"
        export_graph(modules[name], examples[0][name], model, name, path)
        errors[name] = max(validate_graph(path, modules[name], example[name], tolerance=1e-4) for example in examples)
        graphs[name] = graph_entry(path, signatures[name])
    return graphs, errors


def write_licences(bundle_dir: Path, provenance: dict) -> dict:
    """Write the licence text of weights the bundle derives from (the MVSNeRF checkpoint's MIT
    licence must travel with every copy) beside the graphs; the manifest names the file instead."""
    provenance = dict(provenance)
    if isinstance(provenance.get("derived_from"), dict):
        provenance["derived_from"] = dict(provenance["derived_from"])
    for holder in (provenance, provenance.get("derived_from")):
        if isinstance(holder, dict) and holder.get("licence_text"):
            (bundle_dir / holder["licence_file"]).write_text(holder.pop("licence_text"))
    return provenance
