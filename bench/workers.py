"""One measurement per child process, so that peak RSS is per method and per size and the BLAS
thread count is fixed before numpy loads: ``python -m bench.workers KIND ...`` prints one JSON object
on its last stdout line. torch is imported only by the workers that run it, for the same reason."""

from __future__ import annotations

import argparse
import collections
import json
import re
import resource
import time
from pathlib import Path

import numpy as np

from scnerf_export.export.manifest import Manifest, Provenance
from scnerf_export.serving import png_bytes

from . import REPO
from .profile import kernel_events_by_run, kernel_shares
from .scene import read_scene, renderer_run_feeds


def peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # KiB on Linux


def timed(fn) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def worker_gemm(args) -> dict:
    """This machine's fp32 GEMM rate with numpy and with torch at the same thread count."""
    n = args.gemm_n
    rng = np.random.default_rng(0)
    a = rng.standard_normal((n, n), dtype=np.float32)
    b = rng.standard_normal((n, n), dtype=np.float32)
    a @ b  # warm up
    best = min(timed(lambda: a @ b) for _ in range(args.gemm_repeats))
    result = {"n": n, "threads": args.threads, "numpy_gflops": 2.0 * n**3 / best / 1e9, "numpy_seconds": best}
    try:
        from threadpoolctl import threadpool_info  # optional: names the BLAS

        result["blas"] = [
            {k: i.get(k) for k in ("internal_api", "version", "num_threads", "architecture")} for i in threadpool_info()
        ]
    except ImportError:
        result["blas"] = str(np.show_config(mode="dicts").get("Build Dependencies", {}).get("blas", {}))
    import torch

    torch.set_num_threads(args.threads)
    ta, tb = torch.from_numpy(a), torch.from_numpy(b)
    ta @ tb
    best_t = min(timed(lambda: ta @ tb) for _ in range(args.gemm_repeats))
    result["torch_gflops"] = 2.0 * n**3 / best_t / 1e9
    result["peak_rss_mib"] = peak_rss_mib()
    return result


def worker_torch(args) -> dict:
    """PyTorch eager: scnerf_export.runtime.reference (encode_scene split into its two graphs for stage times)."""
    import torch

    from scnerf_export.runtime.reference import build_scene, render_target, source_images

    torch.set_num_threads(args.threads)
    torch.set_num_interop_threads(1)
    t0 = time.perf_counter()
    model, weights_note = load_torch_model(args.bundle, args.checkpoint)
    load_s = time.perf_counter() - t0
    request, images, cameras, target, decode = read_scene(Path(args.scene_dir))
    near, far, bg = request["near"], request["far"], request["background"]
    cfg = model.cfg
    stages = {"decode": decode}
    total0 = time.perf_counter()
    with torch.no_grad():
        imgs = source_images(cfg, images, bg)
        start = time.perf_counter()
        features = model.encode(imgs)
        stages["encoder"] = time.perf_counter() - start
        start = time.perf_counter()
        scene = build_scene(model, imgs, features, cameras, near, far)
        stages["volume"] = time.perf_counter() - start
        start = time.perf_counter()
        result = render_target(model, scene, target, near, far, bg, args.chunk)
        stages["renderer"] = time.perf_counter() - start
    start = time.perf_counter()
    png = png_bytes(result.rgb)
    stages["encode"] = time.perf_counter() - start
    total = time.perf_counter() - total0 + decode
    return finish(args, "torch", stages, total, result.rgb, load_s, {"weights": weights_note, "png_bytes": len(png)})


def worker_ort(args) -> dict:
    """ONNX Runtime from Python: scnerf_export.runtime.onnx_pipeline.OnnxBundle.render_view as is."""
    from scnerf_export.runtime.onnx_pipeline import OnnxBundle

    t0 = time.perf_counter()
    bundle = OnnxBundle(args.bundle, threads=args.threads)
    load_s = time.perf_counter() - t0
    request, images, cameras, target, decode = read_scene(Path(args.scene_dir))
    total0 = time.perf_counter()
    result = bundle.render_view(
        images, cameras, target, request["near"], request["far"], tuple(request["background"]), chunk=args.chunk
    )
    stages = {"decode": decode, **bundle.timings}
    start = time.perf_counter()
    png = png_bytes(result.rgb)
    stages["encode"] = time.perf_counter() - start
    total = time.perf_counter() - total0 + decode
    return finish(args, "ort", stages, total, result.rgb, load_s, {"png_bytes": len(png)})


def worker_profile(args) -> dict:
    """ONNX Runtime's profiler on one renderer run of ``--chunk`` rays of the scene: time per
    operator type (where the renderer's time goes besides its matrix products)."""
    import onnxruntime as ort

    from scnerf_export.runtime.onnx_pipeline import OnnxBundle, session_options

    bundle = OnnxBundle(args.bundle, threads=args.threads)
    feeds = renderer_run_feeds(bundle, Path(args.scene_dir), slice(0, args.chunk))
    options = session_options(args.threads)
    options.enable_profiling = True
    options.profile_file_prefix = str(Path(args.scene_dir).parent / "tmp" / "ort-profile")
    session = ort.InferenceSession(
        str(bundle.graph_path("renderer")),
        options,
        providers=["CPUExecutionProvider"],
    )
    session.run(None, feeds)  # warm-up
    start = time.perf_counter()
    session.run(None, feeds)
    wall = time.perf_counter() - start
    by_op: collections.Counter = collections.Counter()
    for e in kernel_events_by_run(Path(session.end_profiling()))[-1]:
        by_op[e["args"].get("op_name", "?")] += e["dur"]
    by_op_ms = {op: us / 1000.0 for op, us in by_op.most_common()}
    return {"rays": int(feeds["ray_origins"].shape[0]), "wall_ms": wall * 1000.0, **kernel_shares(by_op_ms)}


def finish(args, method: str, stages: dict, total: float, rgb, load_s: float, extra: dict) -> dict:
    if args.save_rgb:
        np.save(args.save_rgb, np.asarray(rgb, np.float32))
    stages_ms = {k: v * 1000.0 for k, v in stages.items()}
    stages_ms["other"] = max(0.0, total * 1000.0 - sum(stages_ms.values()))
    return {
        "method": method,
        "cold_ms": {**stages_ms, "total": total * 1000.0},
        "load_ms": load_s * 1000.0,
        "chunk": args.chunk,
        "threads": args.threads,
        "peak_rss_mib": peak_rss_mib(),
        **extra,
    }


def load_torch_model(bundle_dir: str, checkpoint: str):
    """The PyTorch model behind a bundle: a checkpoint (project or public MVSNeRF), or
    ``random:SEED`` (the parity fixtures' random weights), or ``auto`` (the manifest's provenance:
    random weights with their seed, or ``source_checkpoint`` looked up by name and sha256)."""
    from scnerf_export.model.checkpoint import load_checkpoint, sha256_file
    from scnerf_export.rigs import random_model

    manifest = Manifest.load(bundle_dir)
    cfg, prov = manifest.config, manifest.provenance
    if checkpoint == "auto":
        seed = re.search(r"torch seed (\d+)", str(prov.training or ""))
        if prov.source_kind == "random-weights" and seed:
            checkpoint = f"random:{seed.group(1)}"
        else:
            checkpoint = find_checkpoint(bundle_dir, prov)
    if checkpoint.startswith("random:"):
        return random_model(cfg, int(checkpoint.split(":", 1)[1])).eval(), checkpoint
    model, _ = load_checkpoint(checkpoint)
    note = str(checkpoint)
    if prov.source_sha256 and sha256_file(Path(checkpoint)) != prov.source_sha256:
        note += " (sha256 differs from the bundle's source checkpoint: timings valid, outputs not comparable)"
    if model.cfg != cfg:
        raise SystemExit(f"{checkpoint}: its model config differs from {bundle_dir}'s manifest")
    return model.eval(), note


def find_checkpoint(bundle_dir: str, prov: Provenance) -> str:
    from scnerf_export.model.checkpoint import sha256_file

    name, want = prov.source_checkpoint, prov.source_sha256
    if not name:
        raise SystemExit(f"{bundle_dir}: manifest names no source checkpoint; pass --checkpoint")
    roots = [Path(bundle_dir), REPO, REPO.parent / "shared" / "weights", Path("/work/runs")]
    found = [p for r in roots if r.is_dir() for p in ([r / name] + list(r.glob(f"*/{name}"))) if p.is_file()]
    for path in found:
        if not want or sha256_file(path) == want:
            return str(path)
    if found:
        return str(found[0])  # flagged by load_torch_model
    raise SystemExit(f"source checkpoint {name!r} of {bundle_dir} not found under {roots}; pass --checkpoint")


WORKERS = {"gemm": worker_gemm, "torch": worker_torch, "ort": worker_ort, "profile": worker_profile}


def main(argv=None) -> None:
    p = argparse.ArgumentParser(prog="python -m bench.workers", description=__doc__.split("\n\n")[0])
    p.add_argument("kind", choices=list(WORKERS))
    p.add_argument("--threads", type=int, required=True)
    p.add_argument("--bundle")
    p.add_argument("--checkpoint", default="auto")
    p.add_argument("--scene-dir")
    p.add_argument("--chunk", type=int)
    p.add_argument("--save-rgb")
    p.add_argument("--gemm-n", type=int)
    p.add_argument("--gemm-repeats", type=int)
    args = p.parse_args(argv)
    print(json.dumps(WORKERS[args.kind](args)))


if __name__ == "__main__":
    main()
