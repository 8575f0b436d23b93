"""`python -m bench.thread_layout`: one request's fine runs on 2 cores, one run at a time with 2
threads (the server's layout) against two runs at once with 1 thread each.

DTU scan37's target of ``bench.sampling`` at ``--size`` from its 3 nearest sources; level 0 is
rendered for the rectifier heads, then ``--runs`` chunks of random pixels at ``--samples`` random
samples each (the server's chunk size for that count) go through ``renderer_fine.onnx`` both ways,
in interleaved rounds. Prints microseconds per network sample of each layout and their ratio.

    .venv/bin/python -m bench.thread_layout --samples 16 --rounds 5
"""

from __future__ import annotations

import argparse
import os
import threading
import time
from pathlib import Path

import numpy as np
import onnxruntime as ort

from scnerf_export import cameras as cams
from scnerf_export.runtime import guided
from scnerf_export.runtime.chunks import fine_rays_per_run
from scnerf_export.runtime.onnx_pipeline import OnnxBundle, session_options

from .sampling import encoded_target, write_results
from .scene import parse_sizes


def fine_feeds(bundle: OnnxBundle, name: str, size: tuple[int, int], k: int, runs: int) -> list[dict]:
    """``runs`` chunks of fine-graph inputs over scene ``name``, with level 0's heads."""
    scene, encoded, camera = encoded_target(bundle, name, *size)
    origins, directions = cams.target_rays(camera)
    near, far = scene.near, scene.far
    first = guided.first_level_pixels(camera.width, camera.height, bundle.policy.step)
    level0 = first[:, 0] * camera.width + first[:, 1]
    guide, _ = bundle.guided_runs(encoded, near, far)
    level0_outputs = guide(origins[level0], directions[level0])
    heads = {n: v for n, v in level0_outputs.items() if n.endswith("_heads")}
    fine_inputs = [i.name for i in bundle.sessions["renderer_fine"].get_inputs()]
    chunk = fine_rays_per_run(k, bundle.cfg.samples)
    rng = np.random.default_rng(0)
    found = []
    for _ in range(runs):
        rows = rng.choice(len(origins), chunk, replace=False)
        feeds = bundle.renderer_feeds(encoded, origins[rows], directions[rows], near, far, (near, far))
        index = np.sort(rng.choice(bundle.cfg.samples, (chunk, k)), axis=1).astype(np.float32)
        feeds |= heads | {
            "sample_index": index,
            "sample_multiplicity": np.ones_like(index),
            "head_index": rng.integers(0, len(level0), chunk).astype(np.float32),
        }
        found.append({n: feeds[n] for n in fine_inputs})
    return found


def one_at_a_time(session: ort.InferenceSession, jobs: list[dict]) -> float:
    start = time.perf_counter()
    for feeds in jobs:
        session.run(None, feeds)
    return time.perf_counter() - start


def two_at_once(sessions: list[ort.InferenceSession], jobs: list[dict]) -> float:
    def work(i: int) -> None:
        for feeds in jobs[i :: len(sessions)]:
            sessions[i].run(None, feeds)

    threads = [threading.Thread(target=work, args=(i,)) for i in range(len(sessions))]
    start = time.perf_counter()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return time.perf_counter() - start


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--bundle", default="bundles/default")
    p.add_argument("--size", type=parse_sizes, default=parse_sizes("320x256"))
    p.add_argument("--samples", type=int, default=16)
    p.add_argument("--runs", type=int, default=8)
    p.add_argument("--rounds", type=int, default=5)
    args = p.parse_args()
    bundle = OnnxBundle(args.bundle, threads=2)
    jobs = fine_feeds(bundle, "scan37", args.size[0], args.samples, args.runs)
    path = str(bundle.graph_path("renderer_fine"))
    two_threads = ort.InferenceSession(path, session_options(2), providers=["CPUExecutionProvider"])
    one_thread = [ort.InferenceSession(path, session_options(1), providers=["CPUExecutionProvider"]) for _ in range(2)]
    one_at_a_time(two_threads, jobs[:1])
    two_at_once(one_thread, jobs[:2])
    samples = sum(len(j["sample_index"]) for j in jobs) * args.samples
    rows = []
    for r in range(args.rounds):
        order = [
            ("one run, 2 threads", lambda: one_at_a_time(two_threads, jobs)),
            ("two runs, 1 thread each", lambda: two_at_once(one_thread, jobs)),
        ]
        for label, fn in order if r % 2 == 0 else order[::-1]:
            rows.append({"round": r, "layout": label, "us_per_sample": 1e6 * fn() / samples})
    for label in ("one run, 2 threads", "two runs, 1 thread each"):
        times = [row["us_per_sample"] for row in rows if row["layout"] == label]
        print(f"{label}: median {np.median(times):.2f} us a sample (rounds {', '.join(f'{t:.2f}' for t in times)})")
    ratios = [b["us_per_sample"] / a["us_per_sample"] for a, b in zip(rows[::2], rows[1::2])]
    ratios = [x if rows[2 * i]["layout"] == "one run, 2 threads" else 1 / x for i, x in enumerate(ratios)]
    print(f"two runs / one run per round: median {np.median(ratios):.3f} ({', '.join(f'{x:.3f}' for x in ratios)})")
    results = {"samples": args.samples, "size": args.size[0], "rows": rows, "ratios": ratios, "load": os.getloadavg()}
    print(f"wrote {write_results(results, Path(__file__).parent / 'results', 'thread-layout')}")


if __name__ == "__main__":
    main()
