"""`python -m bench.policy_ab`: guided-sampling policies side by side through the server.

One release server per policy, each serving the bundle with its manifest's ``guided`` object
changed by the policy (the graphs linked, not copied); per scene of ``bench.sampling`` the target's
3 nearest sources are uploaded to each, then every size is rendered by every server in interleaved
rounds (A B C, C B A, ...), so the machine's drift falls on all alike. Per policy: the median and
fastest renderer time (the server's own stage timing), samples per pixel, PSNR and SSIM against
the photo and, with ``--full``, the share of pixels more than 0.25 from full sampling in a channel
and the SSIM against full (full rendered once, by the first server). ``--binary NAME=PATH`` serves
a policy with another server build (the same policy under two builds: an A/B of a change), and
each server's peak resident set (``VmHWM``) is printed at the end.

    .venv/bin/python -m bench.policy_ab --sizes 320x256 --full \\
        'before={"verify_tolerance": null, "verify_share": null}' 'now={}'
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
from contextlib import ExitStack
from pathlib import Path

import numpy as np

from scnerf_export.cameras import camera_json
from scnerf_export.data import datasets
from scnerf_export.evaluate import metrics
from scnerf_export.serving import ServerProcess, find_server_binary

from .sampling import SCENES, SHARED, cropped_target, scene_upload
from .scene import parse_sizes

SPECKLE = 0.25


def policy_bundle(bundle: Path, changes: dict, into: Path) -> Path:
    """``bundle`` with its guided policy changed (keys set to null are removed), in ``into``."""
    into.mkdir(parents=True)
    for f in bundle.iterdir():
        if f.name != "manifest.json":
            (into / f.name).symlink_to(f.resolve())
    manifest = json.loads((bundle / "manifest.json").read_text())
    guided = {**manifest["guided"], **changes}
    manifest["guided"] = {k: v for k, v in guided.items() if v is not None}
    (into / "manifest.json").write_text(json.dumps(manifest, indent=1))
    return into


def compare(servers: dict, scene_name: str, sizes, rounds: int, with_full: bool) -> list[dict]:
    folder, fmt, scale, target = SCENES[scene_name]
    scene = datasets.load_scene(SHARED / folder, fmt, scale=scale)
    uploads = {name: scene_upload(server.client, scene, target)[0] for name, server in servers.items()}
    view = datasets.get_views(scene, [target])[0]
    rows = []
    for width, height in sizes:
        camera, truth = cropped_target(view.camera, view.image, width, height)
        full = None
        if with_full:
            first = next(iter(servers))
            full = servers[first].client.render_scene(uploads[first], camera_json(camera), ["rgb"], sampling="full").rgb
        order = list(servers)
        times = {name: [] for name in servers}
        last = {}
        for r in range(rounds):
            for name in order if r % 2 == 0 else order[::-1]:
                rendered = servers[name].client.render_scene(
                    uploads[name], camera_json(camera), ["rgb"], sampling="guided"
                )
                times[name].append(rendered.timings["renderer"] / 1e3)
                last[name] = rendered
        for name, rendered in last.items():
            row = {
                "scene": f"{scene_name} {target}",
                "size": f"{width}x{height}",
                "policy": name,
                "renderer_s": float(np.median(times[name])),
                "fastest_s": min(times[name]),
                "samples_per_ray": rendered.samples_per_ray,
                "psnr": metrics.psnr(rendered.rgb, truth),
                "ssim": metrics.ssim(rendered.rgb, truth),
            }
            if full is not None:
                row["off_full"] = float((np.abs(rendered.rgb - full).max(axis=2) > SPECKLE).mean())
                row["ssim_to_full"] = metrics.ssim(rendered.rgb, full)
                row["full_psnr"], row["full_ssim"] = metrics.psnr(full, truth), metrics.ssim(full, truth)
            print(json.dumps(row), flush=True)
            rows.append(row)
    return rows


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("policies", nargs="+", help='NAME=JSON: changes to the manifest\'s "guided" object')
    p.add_argument("--bundle", type=Path, default=Path("bundles/default"))
    p.add_argument("--sizes", type=parse_sizes, default=parse_sizes("320x256"))
    p.add_argument("--scenes", type=lambda s: s.split(","), default=list(SCENES))
    p.add_argument("--rounds", type=int, default=2)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--full", action="store_true", help="also compare with full sampling")
    p.add_argument("--binary", action="append", default=[], help="NAME=PATH: the server build for policy NAME")
    args = p.parse_args(argv)
    binaries = dict(item.split("=", 1) for item in args.binary)
    binary = find_server_binary()
    if binary is None:
        raise SystemExit("no scnerf-server binary: cargo build --release -p scnerf-server")
    work = Path(tempfile.mkdtemp(prefix="policy-ab-"))
    try:
        with ExitStack() as stack:
            servers = {}
            for item in args.policies:
                name, _, changes = item.partition("=")
                bundle = policy_bundle(args.bundle, json.loads(changes or "{}"), work / name)
                extra = ("--request-timeout-secs", "7200")
                served_by = binaries.get(name, binary)
                servers[name] = stack.enter_context(ServerProcess(served_by, bundle, threads=args.threads, extra=extra))
            for scene_name in args.scenes:
                compare(servers, scene_name, args.sizes, args.rounds, args.full)
            for name, server in servers.items():
                print(json.dumps({"policy": name, "peak_rss_mib": server.peak_rss_mib()}), flush=True)
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
