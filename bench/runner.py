"""Benchmark one bundle three ways in one run: PyTorch eager (the reference renderer), ONNX Runtime
from Python (the exporter's pipeline) and the Rust server end-to-end over HTTP.

Same bundle, same cameras, same thread count for all three; per stage (decode, encoder, volume,
renderer, encode); cold (one-shot) and cached-scene; ratio of each to PyTorch eager; the renderer's
achieved FLOP/s as a fraction of this machine's fp32 GEMM rate measured in the same run; peak RSS.
See bench/README.md. Run from the repository root with the project's venv:

    .venv/bin/python -m bench --bundle bundles/default --sizes 160x128,320x256

Every measurement runs in a child process of its own (bench.workers); this process only plans the
measurements, derives the figures and writes the report.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import platform
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np

from scnerf_export.export.manifest import Manifest
from scnerf_export.runtime.chunks import rays_per_run
from scnerf_export.runtime.view import renderer_passes
from scnerf_export.serving import find_server_binary

from . import REPO
from .flops import renderer_flops_for
from .report import derive, fmt_stages, keep_fastest, markdown, merge_earlier, recompute_ratios
from .scene import load_png, make_scene_dir, parse_sizes
from .server import bench_server

DEFAULT_SIZES = ("160x128", "320x256", "640x512")
BUSY_PATTERN = r"scnerf-export (train|eval)"


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m bench", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--bundle", default=str(REPO / "bundles/default"))
    p.add_argument(
        "--checkpoint",
        default="auto",
        help="weights of the PyTorch reference: a checkpoint, random:SEED, or auto (from the manifest)",
    )
    p.add_argument(
        "--variant",
        action="append",
        default=[],
        metavar="NAME=DIR",
        help="another bundle of the same network (e.g. int8=bundles/default-int8): ONNX Runtime and "
        "server timings and PSNR against the fp32 outputs",
    )
    p.add_argument("--sizes", default=",".join(DEFAULT_SIZES), help="WxH list, e.g. 160x128,320x256")
    p.add_argument("--variant-sizes", help="sizes at which the --variant bundles run (default: all)")
    p.add_argument("--variant-methods", default="ort,server", help="methods for the --variant bundles")
    p.add_argument("--cached-sizes", help="sizes at which the server also renders a cached scene (default: all)")
    p.add_argument("--threads", type=int, default=os.cpu_count() or 1)
    p.add_argument("--methods", default="torch,ort,server")
    p.add_argument("--chunk", type=int, help="rays per renderer call for the Python paths (default: the server's)")
    p.add_argument("--repeats", type=int, default=1, help="server renders per size (the fastest is kept)")
    p.add_argument(
        "--rounds",
        type=int,
        default=1,
        help="measure every method this many times per size, interleaved, keeping each one's fastest",
    )
    p.add_argument("--server-bin", help="default: target/release/scnerf-server, else target/debug/")
    p.add_argument(
        "--server-arg",
        dest="server_args",
        action="append",
        default=[],
        help="extra server flag (repeatable), e.g. --server-arg=--ort-arena=off",
    )
    p.add_argument(
        "--sampling",
        choices=("full", "guided"),
        default="full",
        help="the server's sampling (PyTorch and ONNX Runtime from Python render in full; "
        "python -m bench.sampling compares the two modes)",
    )
    p.add_argument("--gemm-n", type=int, default=4096)
    p.add_argument("--gemm-repeats", type=int, default=5)
    p.add_argument("--out", default=str(REPO / "bench/results"))
    p.add_argument("--cache", default=str(REPO / "bench/.cache"), help="benchmark scenes")
    p.add_argument("--label", help="free text recorded with the results (default: contended/quiet from the load)")
    p.add_argument("--no-write", action="store_true", help="print only")
    p.add_argument("--report", help="rewrite latest.md (and the ratios) from a results JSON, measuring nothing")
    p.add_argument(
        "--merge",
        help="results JSON of an earlier run of the same bundle: its other sizes/methods are "
        "added to this run's JSON and table (e.g. 640x512 measured separately)",
    )
    p.add_argument(
        "--profile",
        action="store_true",
        help="also profile one renderer chunk per bundle with ONNX Runtime's profiler (time per op type)",
    )
    return p


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    if args.report:
        rewrite_report(args)
        return 0
    results = run(args)
    md = markdown(results)
    print(md)
    if not args.no_write:
        write_results(Path(args.out), results, md)
    return 0


def rewrite_report(args) -> None:
    """latest.md (and the ratios) of a results JSON again, measuring nothing."""
    results = json.loads(Path(args.report).read_text())
    for entry in results["sizes"].values():
        recompute_ratios(entry)
    md = markdown(results)
    print(md)
    if not args.no_write:
        Path(args.report).write_text(json.dumps(results, indent=2, default=float) + "\n")
        (Path(args.out) / "latest.md").write_text(md)


def write_results(out: Path, results: dict, md: str) -> None:
    out.mkdir(parents=True, exist_ok=True)
    started = dt.datetime.fromisoformat(results["started"])
    path = out / f"{started.strftime('%Y%m%d-%H%M')}-{socket.gethostname()}.json"
    path.write_text(json.dumps(results, indent=2, default=float) + "\n")
    (out / "latest.md").write_text(md)
    log(f"wrote {path} and {out / 'latest.md'}")


def run(args) -> dict:
    """Every size of the plan, each method interleaved in ``--rounds`` rounds; then the figures."""
    manifest = Manifest.load(args.bundle)
    chunk = args.chunk or rays_per_run(manifest.config.samples)
    results = start_results(args, manifest, chunk)
    measure_gemm(args, results)
    measured = [
        measure_size(args, results, manifest, width, height, chunk) for width, height in parse_sizes(args.sizes)
    ]
    for entry, rgbs, truth in measured:  # after every GEMM measurement: one rate for all sizes
        derive(entry, results["gemm"]["numpy_gflops"] * 1e9, rgbs, truth)
    results["contention"].update({"busy_processes_after": busy_processes(), "loadavg_after": load()})
    contended = bool(results["contention"]["busy_processes_before"] or results["contention"]["busy_processes_after"])
    results["label"] = args.label or ("contended" if contended else "quiet")
    results["finished"] = dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds")
    if args.merge:
        try:
            merge_earlier(results, json.loads(Path(args.merge).read_text()))
        except ValueError as exc:
            raise SystemExit(f"--merge: {args.merge}: {exc}") from None
    return results


def start_results(args, manifest: Manifest, chunk: int) -> dict:
    """The run's conditions: machine, bundle, plan, contention before it; the server binary found."""
    cfg = manifest.config
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    variants = dict(v.split("=", 1) for v in args.variant)
    server_bin = None
    if "server" in methods or (variants and "server" in args.variant_methods):
        server_bin = find_server_binary(args.server_bin)
        if server_bin is None:
            raise SystemExit("no server binary: cargo build --release -j2 -p scnerf-server (or pass --server-bin)")
        args.server_bin = str(server_bin)
    busy_before, load_before = busy_processes(), load()
    log(f"bundle {args.bundle} ({manifest.model_id}), sizes {args.sizes}, threads {args.threads}, chunk {chunk}")
    if busy_before:
        log(f"CONTENDED: {len(busy_before)} training/eval processes running")
    return {
        "started": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        "machine": machine(),
        "bundle": {
            "dir": args.bundle,
            "model_id": manifest.model_id,
            "variant": manifest.variant,
            "precision": manifest.precision,
            "config": {k: getattr(cfg, k) for k in ("width", "samples", "depth_planes", "views", "pad")},
        },
        "threads": args.threads,
        "rounds": args.rounds,
        "python_chunk": chunk,
        "server_bin": str(server_bin) if server_bin else None,
        "server_args": args.server_args,
        "sampling": args.sampling,
        "methods": methods,
        "variants": variants,
        "variant_precision": {name: Manifest.load(d).precision for name, d in variants.items()},
        "contention": {"busy_processes_before": busy_before, "loadavg_before": load_before},
        "gemm": None,
        "sizes": {},
    }


def measure_size(args, results: dict, manifest: Manifest, width: int, height: int, chunk: int):
    """One size: the renderer's FLOPs, every job in every round, the profile if asked for.
    Returns the size's entry, the fastest round's image of each job, and the ground truth."""
    cfg = manifest.config
    key = f"{width}x{height}"
    scene_dir = make_scene_dir(Path(args.cache), width, height)
    multiple = cfg.image_multiple
    padded = (-(-height // multiple) * multiple, -(-width // multiple) * multiple)
    flops = renderer_flops_for(manifest.graph_path(args.bundle, "renderer"), width * height, padded, cfg.pad)
    flops["flops"] *= renderer_passes(cfg)
    entry: dict = {"rays": width * height, "renderer_gemm_flops": flops, "methods": {}}
    results["sizes"][key] = entry
    tmp = Path(args.cache) / "tmp"
    tmp.mkdir(parents=True, exist_ok=True)
    rgbs = {}
    for round_no in range(1, args.rounds + 1):
        if round_no > 1:
            measure_gemm(args, results)
        for label, method, bundle in jobs(args, results, key):
            log(f"{key}: {label} (round {round_no}/{args.rounds}) ...")
            try:
                r, rgb = run_method(
                    args, method, bundle, scene_dir, chunk, key in cached_sizes(args), tmp / f"{label}-{key}.npy"
                )
            except Exception as exc:  # noqa: BLE001 (record and go on with the other methods)
                log(f"  {label} failed: {exc}")
                entry["methods"].setdefault(label, {"error": str(exc)[-2000:]})
                continue
            log(f"  {label}: " + fmt_stages(r.get("cold_ms", {})))
            if label != method:
                r["variant_of"] = method
            keep_fastest(entry["methods"], label, r)
            if entry["methods"][label] is r:
                rgbs[label] = rgb
    if args.profile and (width, height) == parse_sizes(args.sizes)[0]:
        profile_renderers(args, results, key, scene_dir, chunk)
    return entry, rgbs, load_png(scene_dir / "target_truth.png")


def jobs(args, results: dict, key: str) -> list[tuple[str, str, str]]:
    """(label, method, bundle) of every measurement at a size: the bundle by every method, and the
    --variant bundles by --variant-methods where --variant-sizes includes the size."""
    out = [(m, m, args.bundle) for m in results["methods"]]
    if key in {f"{w}x{h}" for w, h in parse_sizes(args.variant_sizes or args.sizes)}:
        out += [
            (f"{m}-{name}", m, directory)
            for name, directory in results["variants"].items()
            for m in args.variant_methods.split(",")
            if m in ("ort", "server")
        ]
    return out


def cached_sizes(args) -> set[str]:
    return {f"{w}x{h}" for w, h in parse_sizes(args.cached_sizes or args.sizes)}


def profile_renderers(args, results: dict, key: str, scene_dir: Path, chunk: int) -> None:
    """ONNX Runtime's profile of one renderer chunk of the bundle and of each variant."""
    for name, directory in [("fp32", args.bundle), *results["variants"].items()]:
        log(f"{key}: profiling one renderer chunk of {name} ...")
        try:
            results.setdefault("renderer_profile", {})[name] = run_worker(
                args, "profile", ["--bundle", directory, "--scene-dir", str(scene_dir), "--chunk", str(chunk)]
            )
        except Exception as exc:  # noqa: BLE001
            log(f"  profile failed: {exc}")


def measure_gemm(args, results: dict) -> None:
    """The machine's fp32 GEMM rate (numpy, same thread count); over several measurements the
    fastest is kept, so the renderer's fraction of it is never flattered by a slow moment."""
    log("fp32 GEMM rate (numpy, same thread count) ...")
    g = run_worker(args, "gemm", ["--gemm-n", str(args.gemm_n), "--gemm-repeats", str(args.gemm_repeats)])
    log(f"  numpy {g['numpy_gflops']:.0f} GFLOP/s, torch {g['torch_gflops']:.0f} GFLOP/s")
    results.setdefault("gemm_runs_gflops", []).append(g["numpy_gflops"])
    if results.get("gemm") is None or g["numpy_gflops"] > results["gemm"]["numpy_gflops"]:
        results["gemm"] = g


def run_method(args, method: str, bundle: str, scene_dir: Path, chunk: int, cached: bool, rgb_path: Path):
    """One cold view (and, for the server, a cached one) of a bundle by one method: (result, rgb)."""
    if method == "server":
        r = bench_server(args, bundle, scene_dir, cached)
        return r, r.pop("rgb")
    extra = ["--bundle", bundle, "--scene-dir", str(scene_dir), "--chunk", str(chunk), "--save-rgb", str(rgb_path)]
    if method == "torch":
        extra += ["--checkpoint", args.checkpoint]
    r = run_worker(args, method, extra)
    return r, np.load(rgb_path)


def run_worker(args, kind: str, extra: list[str]) -> dict:
    """A bench.workers child process with the BLAS thread count fixed in its environment."""
    cmd = [sys.executable, "-m", "bench.workers", kind, "--threads", str(args.threads), *extra]
    env = dict(os.environ)
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        env[var] = str(args.threads)
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=REPO)
    if proc.returncode != 0:
        raise RuntimeError(f"worker {kind} failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def machine() -> dict:
    info = {"host": socket.gethostname(), "kernel": platform.release(), "python": platform.python_version()}
    try:
        lscpu = subprocess.run(["lscpu"], capture_output=True, text=True).stdout
        fields = dict(line.split(":", 1) for line in lscpu.splitlines() if ":" in line)
        fields = {k.strip(): v.strip() for k, v in fields.items()}
        flags = fields.get("Flags", "").split()
        info.update(
            {
                "cpu": fields.get("Model name"),
                "cpus": int(fields.get("CPU(s)", 0)),
                "threads_per_core": fields.get("Thread(s) per core"),
                "hypervisor": fields.get("Hypervisor vendor"),
                "isa": [f for f in flags if f.startswith(("avx512", "amx", "avx_vnni", "fma", "avx2"))],
                "l2": fields.get("L2 cache"),
                "l3": fields.get("L3 cache"),
            }
        )
    except OSError:
        pass
    for line in Path("/proc/meminfo").read_text().splitlines():
        if line.startswith("MemTotal:"):
            info["memory_gib"] = round(int(line.split()[1]) / 1024**2, 1)
    import numpy
    import onnxruntime
    import torch

    info.update({"numpy": numpy.__version__, "torch": torch.__version__, "onnxruntime": onnxruntime.__version__})
    return info


def busy_processes() -> list[str]:
    proc = subprocess.run(["pgrep", "-af", BUSY_PATTERN], capture_output=True, text=True)
    return [line for line in proc.stdout.splitlines() if str(os.getpid()) != line.split()[0]]


def load() -> list[float]:
    return [round(x, 2) for x in os.getloadavg()]


def log(msg: str) -> None:
    print(f"[{dt.datetime.now().strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)
