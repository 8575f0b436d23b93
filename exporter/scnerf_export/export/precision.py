"""Reduced-precision bundles: `scnerf-export quantize --bundle IN --out OUT --precision int8|fp16`.

A float32 bundle in, a new bundle out whose renderer computes its matrix products in lower
precision (convolutions are left alone: a graph with no matrix product of a constant weight, such
as the encoder, is refused); every graph keeps float32 inputs and outputs, so the server
feeds it exactly as before (docs/bundle.md). The manifest gets a top-level ``"precision"``
(``"int8"``, ``"fp16"``; absent means ``"fp32"``), the new graph hashes and model id, and
``provenance.quantization`` (the source bundle and what was converted).

* ``int8``: ONNX Runtime dynamic quantisation of the MatMul weights, per output channel, signed
  8-bit weights and unsigned 8-bit activations quantised per run (``DynamicQuantizeLinear`` +
  ``MatMulInteger``, fused by ONNX Runtime's CPU provider into ``DynamicQuantizeMatMul``: the
  u8 x s8 kernels that AVX-512 VNNI / AVX-VNNI run). The exporter writes the linear layers as
  ``Gemm``, which dynamic quantisation does not cover, so each ``Gemm`` with a constant weight is
  first rewritten as ``MatMul`` (+ ``Add`` of the bias). Only products with a constant weight and an
  inner size of at least ``min_inner`` are quantised: the camera projections (inner size 3, inputs
  from the request), the activation x activation products of the attention and the products that
  make the attention scores (``products_feeding_softmax``) stay float32.
* ``fp16``: the same matrix products with float16 weights and inputs (a Cast to float16 before,
  back to float32 after); sampling coordinates, encodings and compositing stay float32, where
  float16 would lose sub-pixel positions and high-frequency encodings. The target is the CUDA
  execution provider (tensor cores); ONNX Runtime's CPU provider runs it too.

`compare_bundles` renders the same views through both bundles with ONNX Runtime and reports the
PSNR of each against the ground truth and the drop; ``offer`` = drop <= 0.1 dB (a precision is offered
only within 0.1 dB).
"""

from __future__ import annotations

import datetime as _dt
import shutil
import tempfile
from pathlib import Path

import numpy as np
import onnx
from onnx import helper, numpy_helper

from ..model.checkpoint import sha256_file
from ..runtime.onnx_pipeline import OnnxBundle
from . import onnx_graph
from .external_data import check_holds_its_weights
from .manifest import FLOAT32, Manifest

PRECISIONS = ("fp32", "int8", "fp16")
MAX_PSNR_DROP_DB = 0.1


def gemm_to_matmul(model: onnx.ModelProto) -> int:
    """Rewrite Gemm(A, W, b) with constant W, alpha = beta = 1 and transA = 0 as MatMul(A, W') + b
    (W' = W^T when transB); returns how many were rewritten. Same maths, so float32 outputs match."""
    graph = model.graph
    inits = {t.name: t for t in graph.initializer}
    nodes, count = [], 0
    for node in graph.node:
        attrs = {a.name: helper.get_attribute_value(a) for a in node.attribute}
        if (
            node.op_type != "Gemm"
            or node.input[1] not in inits
            or attrs.get("transA", 0)
            or attrs.get("alpha", 1.0) != 1.0
            or attrs.get("beta", 1.0) != 1.0
        ):
            nodes.append(node)
            continue
        weight = numpy_helper.to_array(inits[node.input[1]])
        if attrs.get("transB", 0):
            weight = weight.T
        wname = f"{node.input[1]}__matmul"
        graph.initializer.append(numpy_helper.from_array(np.ascontiguousarray(weight), wname))
        has_bias = len(node.input) > 2 and node.input[2] != ""
        mm_out = f"{node.output[0]}__matmul" if has_bias else node.output[0]
        nodes.append(helper.make_node("MatMul", [node.input[0], wname], [mm_out], name=f"{node.name}__matmul"))
        if has_bias:
            nodes.append(helper.make_node("Add", [mm_out, node.input[2]], [node.output[0]], name=f"{node.name}__bias"))
        count += 1
    del graph.node[:]
    graph.node.extend(nodes)
    # Drop initializers nothing reads any more (the transposed-away Gemm weights).
    used = {i for n in graph.node for i in n.input} | {o.name for o in graph.output}
    keep = [t for t in graph.initializer if t.name in used]
    del graph.initializer[:]
    graph.initializer.extend(keep)
    return count


def quantizable_matmuls(model: onnx.ModelProto, min_inner: int = 16, exclude: tuple[str, ...] = ()) -> list[str]:
    """MatMul nodes with a constant 2-D weight of inner size >= min_inner, by name, except those
    that compute attention scores."""
    inits = {t.name: t for t in model.graph.initializer}
    scores = products_feeding_softmax(model, inits)
    names = []
    for node in model.graph.node:
        if node.op_type != "MatMul" or node.input[1] not in inits or node.name in scores:
            continue
        dims = list(inits[node.input[1]].dims)
        if len(dims) == 2 and dims[0] >= min_inner and not any(x in node.name for x in exclude):
            names.append(node.name)
    return names


def products_feeding_softmax(model: onnx.ModelProto, inits: dict) -> set[str]:
    """Weight products whose output reaches a Softmax before any other weight product.

    The softmax exponentiates the scores, so an error there is amplified, and per-tensor int8
    activations cannot hold the rectifiers' score terms (query slopes and offsets of very
    different sizes in one tensor: 21 dB against float32 when they were quantised). These
    products are per ray, not per sample, so keeping them float32 costs little."""
    nodes = list(model.graph.node)
    readers = onnx_graph.consumers(nodes)

    def weight_product(node) -> bool:
        return node.op_type in ("MatMul", "Gemm") and any(i in inits for i in node.input)

    found = set()
    for start in nodes:
        if not weight_product(start):
            continue
        frontier, seen = list(start.output), set()
        while frontier:
            for k in readers.get(frontier.pop(), []):
                node = nodes[k]
                if node.op_type == "Softmax":
                    found.add(start.name)
                elif not weight_product(node) and k not in seen:
                    seen.add(k)
                    frontier.extend(node.output)
    return found


def quantize_graph_int8(
    src: Path, dst: Path, min_inner: int = 16, exclude: tuple[str, ...] = (), per_channel: bool = True
) -> dict:
    from onnxruntime.quantization import QuantType, quantize_dynamic

    model = onnx.load(str(src))
    rewritten = gemm_to_matmul(model)
    targets = quantizable_matmuls(model, min_inner, exclude)
    if not targets:
        raise ValueError(f"{src.name}: no MatMul/Gemm with a constant weight to quantise")
    with tempfile.TemporaryDirectory() as tmp:
        staged = Path(tmp) / "float.onnx"
        onnx.save(model, str(staged))
        quantize_dynamic(
            str(staged),
            str(dst),
            per_channel=per_channel,
            reduce_range=False,
            weight_type=QuantType.QInt8,
            nodes_to_quantize=targets,
            op_types_to_quantize=["MatMul"],
            extra_options={"MatMulConstBOnly": True},
        )
    quantized = onnx.load(str(dst))
    onnx_graph.sort_with_outer_scope_reads(quantized.graph)
    onnx.checker.check_model(quantized)
    onnx.save(quantized, str(dst))
    return {
        "method": "onnxruntime.quantization.quantize_dynamic",
        "weight_type": "QInt8",
        "activation_type": "QUInt8 (dynamic, per tensor)",
        "per_channel": per_channel,
        "gemm_rewritten_as_matmul": rewritten,
        "quantized_matmuls": len(targets),
        "min_inner": min_inner,
    }


def convert_graph_fp16(src: Path, dst: Path, min_inner: int = 16, exclude: tuple[str, ...] = ()) -> dict:
    """float16 matrix products: each MatMul with a constant weight (Gemms rewritten first) gets a
    float16 weight, its input cast to float16 and its output cast back to float32; everything
    else (sampling, encodings, compositing) stays float32. One Cast per distinct input tensor."""
    model = onnx.load(str(src))
    rewritten = gemm_to_matmul(model)
    targets = set(quantizable_matmuls(model, min_inner, exclude))
    if not targets:
        raise ValueError(f"{src.name}: no MatMul/Gemm with a constant weight to convert")
    graph = model.graph
    inits = {t.name: t for t in graph.initializer}
    nodes, casts, converted = [], {}, 0
    for node in graph.node:
        if node.name not in targets:
            nodes.append(node)
            continue
        a, w = node.input[0], node.input[1]
        if a not in casts:
            casts[a] = f"{a}__fp16"
            nodes.append(helper.make_node("Cast", [a], [casts[a]], name=f"{a}__to_fp16", to=onnx.TensorProto.FLOAT16))
        w16 = f"{w}__fp16"
        if w16 not in inits:
            inits[w16] = numpy_helper.from_array(numpy_helper.to_array(inits[w]).astype(np.float16), w16)
            graph.initializer.append(inits[w16])
        out16 = f"{node.output[0]}__fp16"
        nodes.append(helper.make_node("MatMul", [casts[a], w16], [out16], name=f"{node.name}__fp16"))
        nodes.append(
            helper.make_node("Cast", [out16], [node.output[0]], name=f"{node.name}__to_fp32", to=onnx.TensorProto.FLOAT)
        )
        converted += 1
    del graph.node[:]
    graph.node.extend(nodes)
    used = {i for n in graph.node for i in n.input}
    keep = [t for t in graph.initializer if t.name in used]
    del graph.initializer[:]
    graph.initializer.extend(keep)
    onnx.checker.check_model(model)
    onnx.save(model, str(dst))
    return {
        "method": "float16 MatMul weights and inputs (Cast before, Cast back to float32 after), float32 elsewhere",
        "gemm_rewritten_as_matmul": rewritten,
        "fp16_matmuls": converted,
        "min_inner": min_inner,
    }


def quantize_bundle(
    src_dir: str | Path,
    out_dir: str | Path,
    precision: str,
    graphs: tuple[str, ...] = ("renderer",),
    min_inner: int = 16,
    exclude: tuple[str, ...] = (),
) -> Manifest:
    """Write a copy of the float32 bundle ``src_dir`` to ``out_dir`` with ``graphs`` converted to
    ``precision``; returns the new manifest."""
    if precision not in ("int8", "fp16"):
        raise ValueError(f"precision must be int8 or fp16, got {precision!r}")
    src, out = Path(src_dir), Path(out_dir)
    manifest = Manifest.load(src)
    if manifest.precision != FLOAT32:
        raise ValueError(f"{src} is already {manifest.precision}: start from a float32 bundle")
    unknown = set(graphs) - set(manifest.graphs)
    if unknown:
        raise ValueError(f"unknown graphs {sorted(unknown)} (bundle has {sorted(manifest.graphs)})")
    if out.resolve() == src.resolve():
        raise ValueError("--out must differ from --bundle")
    out.mkdir(parents=True, exist_ok=True)
    details = {}
    for name, entry in manifest.graphs.items():
        source_file, target_file = src / entry.file, out / entry.file
        if sha256_file(source_file) != entry.sha256:
            raise ValueError(f"{source_file}: sha256 does not match the manifest")
        if name in graphs:
            if precision == "int8":
                details[name] = quantize_graph_int8(source_file, target_file, min_inner, exclude)
            else:
                details[name] = convert_graph_fp16(source_file, target_file, min_inner, exclude)
        else:
            shutil.copyfile(source_file, target_file)
        check_holds_its_weights(target_file)
        entry.sha256 = sha256_file(target_file)
    source_model_id = manifest.model_id
    manifest.model_id = manifest.expected_model_id()
    manifest.precision = precision
    manifest.provenance.quantization = {
        "precision": precision,
        "source_model_id": source_model_id,
        "graphs": details,
        "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
    }
    manifest.save(out)
    return manifest


def verify_bundle_hashes(bundle_dir: str | Path) -> None:
    manifest = Manifest.load(bundle_dir)
    for name, entry in manifest.graphs.items():
        if sha256_file(Path(bundle_dir) / entry.file) != entry.sha256:
            raise ValueError(f"{bundle_dir}: graphs.{name} sha256 mismatch")
    expected = manifest.expected_model_id()
    if manifest.model_id != expected:
        raise ValueError(f"{bundle_dir}: model_id {manifest.model_id} != {expected}")


# ---------------------------------------------------------------------------------------------
# quality: PSNR of the reduced-precision bundle against the float32 one


def procedural_cases(count: int = 4, width: int = 160, height: int = 128, seed_offset: int = 5000) -> list[dict]:
    """Held-out procedural views (validation seeds), one per scene, layouts in turn: images,
    cameras, target camera, near/far and the ray-traced ground truth."""
    from ..data.procedural import LAYOUTS
    from ..data.procedural.dataset import VAL_SEED0
    from ..data.procedural.layouts import build_layout
    from ..data.procedural.raytrace import render_view
    from ..data.procedural.scenes import pick_camera_sources

    cases = []
    for i in range(count):
        layout, seed, target = LAYOUTS[i % len(LAYOUTS)], VAL_SEED0 + seed_offset + i, 5
        world, cameras, near, far = build_layout(seed, layout, 12, width, height)
        sources = pick_camera_sources(cameras, target, gap="small")
        views = [render_view(world, cameras[k], supersample=2) for k in sources + [target]]
        cases.append(
            {
                "name": f"{layout}-{seed}",
                "images": np.stack([v.image for v in views[:3]]),
                "cameras": [cameras[k] for k in sources],
                "target": cameras[target],
                "near": near,
                "far": far,
                "background": (0.0, 0.0, 0.0),
                "truth": views[3].image,
            }
        )
    return cases


def compare_bundles(
    reference_dir: str | Path,
    candidate_dir: str | Path,
    cases: list[dict],
    threads: int | None = None,
    chunk: int | None = None,
) -> dict:
    import time

    from ..evaluate.metrics import psnr

    ref, cand = OnnxBundle(reference_dir, threads), OnnxBundle(candidate_dir, threads)
    rows = []
    for case in cases:
        args = (case["images"], case["cameras"], case["target"], case["near"], case["far"], case["background"], chunk)
        t0 = time.perf_counter()
        a = ref.render_view(*args)
        t1 = time.perf_counter()
        b = cand.render_view(*args)
        t2 = time.perf_counter()
        ref_r, cand_r = ref.timings.get("renderer", 0.0), cand.timings.get("renderer", 0.0)
        rows.append(
            {
                "case": case["name"],
                "psnr_fp32": psnr(a.rgb, case["truth"]),
                "psnr_candidate": psnr(b.rgb, case["truth"]),
                "psnr_candidate_vs_fp32": psnr(b.rgb, a.rgb),
                "max_abs_diff": float(np.abs(a.rgb - b.rgb).max()),
                "seconds_fp32": t1 - t0,
                "seconds_candidate": t2 - t1,
                "renderer_seconds_fp32": ref_r,
                "renderer_seconds_candidate": cand_r,
            }
        )
        rows[-1]["psnr_drop"] = rows[-1]["psnr_fp32"] - rows[-1]["psnr_candidate"]
    mean = {k: float(np.mean([r[k] for r in rows])) for k in rows[0] if k != "case"}
    drop = mean["psnr_fp32"] - mean["psnr_candidate"]
    return {
        "reference": str(reference_dir),
        "candidate": str(candidate_dir),
        "precision": cand.manifest.precision,
        "rows": rows,
        "mean": mean,
        "psnr_drop_db": drop,
        "renderer_speedup": mean["renderer_seconds_fp32"] / max(mean["renderer_seconds_candidate"], 1e-9),
        "offer": bool(drop <= MAX_PSNR_DROP_DB),
        "rule": f"offer only if the mean PSNR drop <= {MAX_PSNR_DROP_DB} dB",
    }
