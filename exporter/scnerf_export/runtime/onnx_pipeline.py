"""A bundle run by ONNX Runtime from Python: the same stages and inputs as the Rust server."""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
import onnxruntime as ort

from .. import cameras as cams
from ..cameras import Camera
from ..export.manifest import Manifest
from .band import FILLS, fill_rendering
from .chunks import fine_rays_per_run, rays_per_run
from .guided import FineRun, GuideRun, guided_rendering
from .plane_sweep import sweep
from .view import Rendering, pad_images, render_in_passes
from .volume_slabs import Sweep, build_volume


def session_options(threads: int | None) -> ort.SessionOptions:
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads or os.cpu_count() or 1
    options.inter_op_num_threads = 1
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    return options


class OnnxBundle:
    def __init__(self, bundle_dir: str | Path, threads: int | None = None, plane_sweep: Sweep = sweep):
        """``plane_sweep``: how a bundle that leaves the plane sweep to the server computes it
        (default: the server's arithmetic, in numpy)."""
        self.path = Path(bundle_dir)
        self.plane_sweep = plane_sweep
        self.manifest = Manifest.load(self.path)
        self.cfg = self.manifest.config
        options = session_options(threads)
        self.sessions = {
            name: ort.InferenceSession(str(self.path / g.file), options, providers=["CPUExecutionProvider"])
            for name, g in self.manifest.graphs.items()
        }
        self.renderer_inputs = [i.name for i in self.sessions["renderer"].get_inputs()]
        self.policy = self.manifest.guided
        self.timings: dict[str, float] = {}
        self.graph_seconds: dict[str, float] = {}  # per graph, summed over every run

    @property
    def model_id(self) -> str:
        return self.manifest.model_id

    def graph_path(self, name: str) -> Path:
        return self.manifest.graph_path(self.path, name)

    def _timed(self, stage: str, graph: str, feeds: dict) -> list[np.ndarray]:
        start = time.perf_counter()
        out = self.sessions[graph].run(None, feeds)
        seconds = time.perf_counter() - start
        self.timings[stage] = self.timings.get(stage, 0.0) + seconds
        self.graph_seconds[graph] = self.graph_seconds.get(graph, 0.0) + seconds
        return out

    def encode_scene(
        self, images: np.ndarray, cameras: list[Camera], near: float, far: float, background
    ) -> dict[str, np.ndarray]:
        padded = pad_images(images.astype(np.float32), self.cfg.image_multiple, background)
        imgs = np.ascontiguousarray(padded.transpose(0, 3, 1, 2))
        (features,) = self._timed("encoder", "encoder", {"images": imgs})
        feeds = {
            "features": features,
            "images": imgs,
            "projections": cams.feature_projections(cameras),
            "depth_planes": cams.depth_planes(near, far, self.cfg.depth_planes),
        }
        start = time.perf_counter()
        volume = build_volume(self.sessions, feeds, self.cfg, plane_sweep=self.plane_sweep)
        self.timings["volume"] = self.timings.get("volume", 0.0) + time.perf_counter() - start
        return {
            "images": imgs,
            "features": features,
            "volume": volume,
            "intrinsics": cams.stack_intrinsics(cameras),
            "extrinsics": cams.stack_extrinsics(cameras),
            "source_sizes": [(c.width, c.height) for c in cameras],
        }

    def renderer_feeds(
        self,
        scene: dict,
        origins: np.ndarray,
        directions: np.ndarray,
        near: float,
        far: float,
        depth_range: tuple[float, float],
    ) -> dict[str, np.ndarray]:
        """The renderer's inputs for one run of rays of an encoded scene."""
        given = {
            **scene,
            "near_far": np.array([near, far], np.float32),
            "depth_range": np.array(depth_range, np.float32),
            "ray_origins": np.ascontiguousarray(origins),
            "ray_directions": np.ascontiguousarray(directions),
        }
        return {name: given[name] for name in self.renderer_inputs}

    def render_rays(
        self,
        scene: dict,
        origins: np.ndarray,
        directions: np.ndarray,
        near: float,
        far: float,
        depth_range: tuple[float, float],
        chunk: int | None = None,
    ):
        """Raw rgb, depth, opacity of the rays, ``chunk`` rays per run (default: the server's)."""
        chunk = chunk or rays_per_run(self.cfg.samples)
        outs = []
        for start in range(0, origins.shape[0], chunk):
            rays = slice(start, start + chunk)
            feeds = self.renderer_feeds(scene, origins[rays], directions[rays], near, far, depth_range)
            outs.append(self._timed("renderer", "renderer", feeds))
        return tuple(np.concatenate([o[i] for o in outs]) for i in range(3))

    def render_view(
        self,
        images: np.ndarray,
        cameras: list[Camera],
        target: Camera,
        near: float,
        far: float,
        background=(0.0, 0.0, 0.0),
        chunk: int | None = None,
        band: str = "sources",
    ) -> Rendering:
        self.timings = {}
        scene = self.encode_scene(images, cameras, near, far, background)
        return self.render_target(scene, target, near, far, background, chunk, band=band)

    def render_target(
        self,
        scene: dict,
        target: Camera,
        near: float,
        far: float,
        background=(0.0, 0.0, 0.0),
        chunk: int | None = None,
        sampling: str = "full",
        band: str = "sources",
    ) -> Rendering:
        """One target view of an encoded scene (what a cached scene costs per view), with the
        paper's S samples per ray (``full``) or guided sampling (``guided``, runtime/guided.py);
        the band's pixels coloured as the server's ``--band`` does (runtime/band.py)."""
        if sampling == "guided":
            rendering = self.render_guided(scene, target, near, far, background)
        else:

            def rays(origins, directions, depth_range):
                return self.render_rays(scene, origins, directions, near, far, depth_range, chunk)

            rendering = render_in_passes(self.cfg, target, near, far, background, rays)
        if band == "sources":
            rendering = fill_rendering(rendering, target, scene, background, self.manifest.band)
        elif band != "network":
            raise ValueError(f"band must be one of {', '.join(FILLS)}, got {band!r}")
        return rendering

    def render_guided(self, scene: dict, target: Camera, near: float, far: float, background) -> Rendering:
        """A view by guided sampling, run as the server runs it."""
        if self.policy is None:
            raise ValueError(f"{self.path}: the bundle has no guided-sampling graphs (scnerf-export add-guided)")
        guide, fine = self.guided_runs(scene, near, far)
        return guided_rendering(self.policy, self.cfg, target, background, guide, fine)

    def guided_runs(self, scene: dict, near: float, far: float) -> tuple[GuideRun, FineRun]:
        """Guided sampling's two graphs over an encoded scene, in the server's chunks: a guide run
        keeps its rays' rectifier heads, which the fine runs after it read."""
        depth_range = (near, far)
        guide_inputs = [i.name for i in self.sessions["renderer_guide"].get_inputs()]
        fine_inputs = [i.name for i in self.sessions["renderer_fine"].get_inputs()]
        guide_outputs = [o.name for o in self.sessions["renderer_guide"].get_outputs()]
        heads: dict[str, np.ndarray] = {}

        def guide(origins, directions):
            outs = []
            step = rays_per_run(self.cfg.samples)
            for start in range(0, origins.shape[0], step):
                rays = slice(start, start + step)
                feeds = self.renderer_feeds(scene, origins[rays], directions[rays], near, far, depth_range)
                outs.append(self._timed("renderer", "renderer_guide", {n: feeds[n] for n in guide_inputs}))
            out = {name: np.concatenate([o[i] for o in outs]) for i, name in enumerate(guide_outputs)}
            heads.update({k: v for k, v in out.items() if k.endswith("_heads")})
            return {"weights": out["sample_weights"], **out}

        def fine(origins, directions, index, multiplicity, guide_rows):
            step = fine_rays_per_run(index.shape[1], self.cfg.samples)
            outs = []
            for start in range(0, origins.shape[0], step):
                rays = slice(start, start + step)
                feeds = self.renderer_feeds(scene, origins[rays], directions[rays], near, far, depth_range)
                feeds |= heads | {
                    "sample_index": index[rays],
                    "sample_multiplicity": multiplicity[rays],
                    "head_index": guide_rows[rays],
                }
                outs.append(self._timed("renderer", "renderer_fine", {n: feeds[n] for n in fine_inputs}))
            names = ("rgb", "depth", "opacity", "weights")
            return {name: np.concatenate([o[i] for o in outs]) for i, name in enumerate(names)}

        return guide, fine
