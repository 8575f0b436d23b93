"""The rectifiers' attention core in ONNX Runtime, written the ways its ops allow.

Per ray and head, the core is softmax over key tokens of [q_c, 1] . [slope_c', offset_c'] (inner
size 2, see SampleAxisAttention) times the values: (R, h, C, C) scores for R rays. The renderer
graph runs it as MatMul -> Softmax -> MatMul(V, A^T). This times, at the default bundle's sizes,
that chain and its ops alone, against ONNX's Attention (opset 23, 4-D and 3-D inputs),
com.microsoft's MultiHeadAttention, and the chain inside a Loop over groups of rays as the
exporter writes it (each group's scores small enough for the cache). Every variant is checked
against the chain.

    .venv/bin/python -m bench.attention_core --rays 512 --rounds 30 --groups 16,32,64
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import onnx
import onnxruntime as ort
from onnx import TensorProto, helper

from scnerf_export.export.ray_groups import attention_cores_in_ray_groups
from scnerf_export.runtime.onnx_pipeline import session_options

HEADS, HEAD_DIM, TOKENS = 4, 8, 64  # the default bundle's h, d_k and width C


def model(nodes, inputs: dict, opsets=(("", 18),)) -> onnx.ModelProto:
    """A graph of `nodes` whose output `y` is sliced to one ray: only the core's work is timed,
    not the copy of a large graph output."""
    first = [
        helper.make_node("Constant", [], [n], value=helper.make_tensor(n, TensorProto.INT64, [1], [v]))
        for n, v in (("zero", 0), ("one", 1))
    ]
    nodes = [*first, *nodes, helper.make_node("Slice", ["y", "zero", "one", "zero"], ["out"])]
    graph = helper.make_graph(
        nodes,
        "core",
        [helper.make_tensor_value_info(n, TensorProto.FLOAT, a.shape) for n, a in inputs.items()],
        [helper.make_tensor_value_info("out", TensorProto.FLOAT, None)],
    )
    return helper.make_model(graph, opset_imports=[helper.make_opsetid(d, v) for d, v in opsets], ir_version=10)


def chain(prefix: str, qa: str, so: str, vt: str, out: str) -> list:
    return [
        helper.make_node("MatMul", [qa, so], [prefix + "scores"]),
        helper.make_node("Softmax", [prefix + "scores"], [prefix + "attention"], axis=-1),
        helper.make_node("Transpose", [prefix + "attention"], [prefix + "attention_t"], perm=[0, 1, 3, 2]),
        helper.make_node("MatMul", [vt, prefix + "attention_t"], [out]),
    ]


def in_ray_groups(graph: onnx.ModelProto, group: int) -> onnx.ModelProto:
    """The chain as the exporter writes it into the renderer (scnerf_export.export.ray_groups)."""
    attention_cores_in_ray_groups(graph, rays_per_group=group)
    return graph


def variants(rays: int, groups: list[int], rng) -> list:
    """(name, graph, feeds, to_chain_layout) per formulation; to_chain_layout maps a variant's
    output to the chain's (rays, h, d_k, C), None for the single ops (not a whole core)."""
    r, h, dk, c = rays, HEADS, HEAD_DIM, TOKENS
    q = rng.standard_normal((r, c), np.float32)
    qa = np.stack([q, np.ones_like(q)], -1)[:, None]  # (R,1,C,2)
    so = rng.standard_normal((r, h, 2, c), np.float32) * 2  # slopes and offsets
    vt = rng.standard_normal((r, h, dk, c), np.float32)
    a = rng.standard_normal((r, h, c, c), np.float32)
    v4 = vt.transpose(0, 1, 3, 2).copy()
    per_head = {"q": np.broadcast_to(qa, (r, h, c, 2)).copy(), "k": so.transpose(0, 1, 3, 2).copy(), "v": v4}
    heads_in_hidden = {
        "q": per_head["q"].transpose(0, 2, 1, 3).reshape(r, c, 2 * h).copy(),
        "k": so.transpose(0, 3, 1, 2).reshape(r, c, 2 * h).copy(),
        "v": vt.transpose(0, 3, 1, 2).reshape(r, c, h * dk).copy(),
    }
    core = {"qa": qa, "so": so, "vt": vt}

    def from_hidden(y):
        return y.reshape(-1, c, h, dk).transpose(0, 2, 3, 1)

    def attention(**kw):
        return [helper.make_node("Attention", ["q", "k", "v"], ["y"], scale=1.0, **kw)]

    return [
        ("chain (the graph's)", model(chain("", "qa", "so", "vt", "y"), core), core, lambda y: y),
        (
            "  scores alone (K = 2)",
            model([helper.make_node("MatMul", ["qa", "so"], ["y"])], {"qa": qa, "so": so}),
            {"qa": qa, "so": so},
            None,
        ),
        ("  softmax alone", model([helper.make_node("Softmax", ["a"], ["y"], axis=-1)], {"a": a}), {"a": a}, None),
        (
            "  V A^T alone",
            model(
                [
                    helper.make_node("Transpose", ["a"], ["at"], perm=[0, 1, 3, 2]),
                    helper.make_node("MatMul", ["vt", "at"], ["y"]),
                ],
                {"vt": vt, "a": a},
            ),
            {"vt": vt, "a": a},
            None,
        ),
        (
            "  A V alone (V: tokens x d_k)",
            model([helper.make_node("MatMul", ["a", "v"], ["y"])], {"a": a, "v": v4}),
            {"a": a, "v": v4},
            None,
        ),
        ("Attention-23, 4-D", model(attention(), per_head, (("", 23),)), per_head, lambda y: y.transpose(0, 1, 3, 2)),
        (
            "Attention-23, 3-D",
            model(attention(q_num_heads=h, kv_num_heads=h), heads_in_hidden, (("", 23),)),
            heads_in_hidden,
            from_hidden,
        ),
        (
            "MultiHeadAttention (contrib)",
            model(
                [
                    helper.make_node(
                        "MultiHeadAttention", ["q", "k", "v"], ["y"], domain="com.microsoft", num_heads=h, scale=1.0
                    )
                ],
                heads_in_hidden,
                (("", 18), ("com.microsoft", 1)),
            ),
            heads_in_hidden,
            from_hidden,
        ),
        *[
            (
                f"chain in a Loop, {g} rays a turn",
                in_ray_groups(model(chain("", "qa", "so", "vt", "y"), core), g),
                core,
                lambda y: y,
            )
            for g in groups
        ],
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rays", type=int, default=512)
    parser.add_argument("--rounds", type=int, default=30)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--groups", default="16,32,64", help="ray groups of the Loop variants")
    args = parser.parse_args()
    options = session_options(args.threads)
    options.add_session_config_entry("session.intra_op.allow_spinning", "0")  # see bench/ab.py
    groups = [int(g) for g in args.groups.split(",")]
    cases = [
        (
            name,
            ort.InferenceSession(graph.SerializeToString(), options, providers=["CPUExecutionProvider"]),
            feeds,
            layout,
            [],
        )
        for name, graph, feeds, layout in variants(args.rays, groups, np.random.default_rng(0))
    ]
    for _ in range(args.rounds):
        for _, session, feeds, _, spent in cases:
            start = time.perf_counter()
            session.run(None, feeds)
            spent.append(time.perf_counter() - start)
    reference = cases[0][1].run(None, cases[0][2])[0]
    print(
        f"{args.rays} rays, {args.threads} threads, {args.rounds} interleaved rounds, ms per run "
        "(max |difference| from the chain on the first ray):"
    )
    for name, session, feeds, layout, spent in cases:
        ms = np.array(spent) * 1e3
        check = "" if layout is None else f"  ({np.abs(layout(session.run(None, feeds)[0]) - reference).max():.1e})"
        print(f"  {name:34s} fastest {ms.min():6.2f}  median {np.median(ms):6.2f}{check}")


if __name__ == "__main__":
    main()
