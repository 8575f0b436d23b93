"""The renderer's FLOPs, counted on its ONNX graph: the work a view costs, for the achieved FLOP/s."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
from onnx import shape_inference

from scnerf_export.export.ray_groups import plain_attention_cores


def renderer_gemm_flops(onnx_path: Path, rays: int, hw: tuple[int, int], pad: int) -> dict:
    """Sum of 2*M*N*K over the renderer's MatMul/Gemm nodes (batch dims multiplied in), with every
    shape from ONNX shape inference (data propagation on) at R = ``rays`` and the given padded
    source size. Every MatMul/Gemm of the renderer is per ray, so the count is exactly linear in R.
    Shape inference does not look inside a Loop, so the attention cores that the graph runs a
    group of rays at a time are counted as their plain chains (the same products)."""
    model = onnx.load(str(onnx_path))
    plain_attention_cores(model)
    H, W = hw
    dims = {"R": rays, "H": H, "W": W, "h": H // 4, "w": W // 4, "Hp": H // 4 + 2 * pad, "Wp": W // 4 + 2 * pad}
    for value in model.graph.input:
        for d in value.type.tensor_type.shape.dim:
            if d.dim_param:
                size = dims[d.dim_param]
                d.ClearField("dim_param")
                d.dim_value = size
    inferred = shape_inference.infer_shapes(model, data_prop=True)
    shapes = {t.name: list(t.dims) for t in inferred.graph.initializer}
    for v in list(inferred.graph.value_info) + list(inferred.graph.input) + list(inferred.graph.output):
        shapes[v.name] = [d.dim_value if d.HasField("dim_value") else None for d in v.type.tensor_type.shape.dim]
    total, nodes, unknown = 0, 0, []
    for node in inferred.graph.node:
        if node.op_type not in ("MatMul", "Gemm"):
            continue
        a, b = shapes.get(node.input[0]), shapes.get(node.input[1])
        if not a or not b or None in a or None in b:
            unknown.append(node.name)
            continue
        if node.op_type == "Gemm":
            attrs = {x.name: x.i for x in node.attribute}
            m, k = (a[1], a[0]) if attrs.get("transA") else (a[0], a[1])
            n = b[0] if attrs.get("transB") else b[1]
            flops = 2 * m * n * k
        else:
            if len(a) == 1:
                a = [1] + a
            if len(b) == 1:
                b = b + [1]
            batch = np.broadcast_shapes(tuple(a[:-2]), tuple(b[:-2]))
            flops = 2 * int(np.prod(batch)) * a[-2] * a[-1] * b[-1]
        total += flops
        nodes += 1
    return {"flops": total, "rays": rays, "matmul_gemm_nodes": nodes, "unresolved_nodes": unknown}


def renderer_flops_for(onnx_path: Path, rays: int, hw: tuple[int, int], pad: int) -> dict:
    """renderer_gemm_flops at R = 512 and 1024 (shape inference with data propagation needs memory
    that grows with R), checked to be exactly linear in R, scaled to ``rays``."""
    a = renderer_gemm_flops(onnx_path, 512, hw, pad)
    b = renderer_gemm_flops(onnx_path, 1024, hw, pad)
    if b["flops"] != 2 * a["flops"] or a["unresolved_nodes"]:
        raise RuntimeError(f"renderer FLOPs not linear in R or shapes unresolved: {a} {b}")
    return {
        **b,
        "flops": b["flops"] * rays // 1024,
        "rays": rays,
        "counted_at_rays": 1024,
        "per_ray": b["flops"] / 1024,
    }
