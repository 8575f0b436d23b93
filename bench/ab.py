"""Interleaved A/B of renderer graphs: the sessions take turns, one renderer run each per round.

The benchmark (python -m bench) times whole views one after another, so a drift of the machine's speed between them
(10-30 % within minutes on a shared KVM guest) is as large as most graph changes. Here every
round runs each bundle's renderer once on the same rays, so a drift shifts all of them alike.

Each session has its own intra-op thread pool (Python's onnxruntime cannot share one, as the
server's sessions do), so spinning is off by default: a pool whose workers spin after its run
takes a core from the next session's run, which made medians 3-5x the fastest round on 2 cores.

    .venv/bin/python -m bench.ab bundles/default /tmp/candidate --rounds 40
    .venv/bin/python -m bench.ab bundles/default bundles/default@session.set_denormal_as_zero=1

A bundle may carry ONNX Runtime session config entries after '@' (key=value, '@'-separated).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import onnxruntime as ort

from scnerf_export.runtime.onnx_pipeline import OnnxBundle, session_options

from . import REPO
from .scene import renderer_run_feeds

EXAMPLE = REPO / "examples" / "tabletop"


def renderer_run(spec: str, threads: int, spin: bool, first_ray: int, rays: int):
    """(session, feeds) for one bundle spec 'DIR[@key=value...]' on a fixed slice of the rays."""
    path, *entries = spec.split("@")
    bundle = OnnxBundle(path, threads=1)
    options = session_options(threads)
    options.add_session_config_entry("session.intra_op.allow_spinning", "1" if spin else "0")
    for entry in entries:
        key, value = entry.split("=", 1)
        options.add_session_config_entry(key, value)
    renderer = bundle.graph_path("renderer")
    session = ort.InferenceSession(str(renderer), options, providers=["CPUExecutionProvider"])
    return session, renderer_run_feeds(bundle, EXAMPLE, slice(first_ray, first_ray + rays))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("bundles", nargs="+", help="bundle directories, each optionally @key=value...")
    parser.add_argument("--rounds", type=int, default=40)
    parser.add_argument(
        "--rays",
        default="512",
        help="rays per run (the server's default chunk); a list (64,512) times each bundle at each",
    )
    parser.add_argument("--first-ray", type=int, default=20000, help="where the slice starts (inside the object)")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--spin", action="store_true", help="let idle workers spin (see the module docstring)")
    args = parser.parse_args()

    entries = [(spec, int(rays)) for spec in args.bundles for rays in args.rays.split(",")]
    runs = [renderer_run(spec, args.threads, args.spin, args.first_ray, rays) for spec, rays in entries]
    for session, feeds in runs:  # first runs allocate the arenas
        session.run(None, feeds)
    times = [[] for _ in runs]
    for _ in range(args.rounds):
        for (session, feeds), spent in zip(runs, times):
            start = time.perf_counter()
            session.run(None, feeds)
            spent.append(time.perf_counter() - start)
    reference = runs[0][0].run(None, runs[0][1])[0]
    for (spec, rays), (session, feeds), spent in zip(entries, runs, times):
        per_ray = np.array(spent) * 1e6 / rays
        rgb = session.run(None, feeds)[0]
        shared = min(len(rgb), len(reference))
        print(
            f"{spec:40s} {rays:5d} rays: fastest {per_ray.min():6.1f}  p25 {np.quantile(per_ray, 0.25):6.1f}  "
            f"median {np.median(per_ray):6.1f} µs/ray  max |rgb - first| "
            f"{np.abs(rgb[:shared] - reference[:shared]).max():.1e}"
        )


if __name__ == "__main__":
    main()
