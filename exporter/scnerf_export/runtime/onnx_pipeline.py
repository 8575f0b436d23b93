"""A bundle run by ONNX Runtime from Python: the same stages and inputs as the Rust server."""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
import onnxruntime as ort

from .. import cameras as cams
from ..cameras import Camera
from ..config import ModelConfig
from ..export.manifest import read_manifest
from .view import Rendering, pad_images


# Rays per renderer run, the server's default (DEFAULT_MAX_RAYS in server/src/pipeline/chunks.rs): small
# runs keep the renderer's activations in cache.
DEFAULT_CHUNK = 512


def session_options(threads: int | None) -> ort.SessionOptions:
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads or os.cpu_count() or 1
    options.inter_op_num_threads = 1
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    return options


class OnnxBundle:
    def __init__(self, bundle_dir: str | Path, threads: int | None = None):
        self.path = Path(bundle_dir)
        self.manifest = read_manifest(self.path)
        self.cfg = ModelConfig.from_dict(self.manifest["config"])
        options = session_options(threads)
        self.sessions = {
            name: ort.InferenceSession(str(self.path / g["file"]), options, providers=["CPUExecutionProvider"])
            for name, g in self.manifest["graphs"].items()
        }
        self.renderer_inputs = [i.name for i in self.sessions["renderer"].get_inputs()]
        self.timings: dict[str, float] = {}

    def _timed(self, stage: str, graph: str, feeds: dict) -> list[np.ndarray]:
        start = time.perf_counter()
        out = self.sessions[graph].run(None, feeds)
        self.timings[stage] = self.timings.get(stage, 0.0) + time.perf_counter() - start
        return out

    def encode_scene(self, images: np.ndarray, cameras: list[Camera], near: float, far: float,
                     background) -> dict[str, np.ndarray]:
        padded = pad_images(images.astype(np.float32), self.cfg.image_multiple, background)
        imgs = np.ascontiguousarray(padded.transpose(0, 3, 1, 2))
        (features,) = self._timed("encoder", "encoder", {"images": imgs})
        (volume,) = self._timed("volume", "volume", {
            "features": features, "images": imgs, "projections": cams.feature_projections(cameras),
            "depth_planes": cams.depth_planes(near, far, self.cfg.depth_planes)})
        return {"images": imgs, "features": features, "volume": volume,
                "intrinsics": cams.stack_intrinsics(cameras), "extrinsics": cams.stack_extrinsics(cameras)}

    def render_rays(self, scene: dict, origins: np.ndarray, directions: np.ndarray, near: float, far: float,
                    depth_range: tuple[float, float], chunk: int):
        fixed = {**scene, "near_far": np.array([near, far], np.float32),
                 "depth_range": np.array(depth_range, np.float32)}
        outs = []
        for start in range(0, origins.shape[0], chunk):
            feeds = {name: fixed[name] for name in self.renderer_inputs if name in fixed}
            feeds["ray_origins"] = np.ascontiguousarray(origins[start : start + chunk])
            feeds["ray_directions"] = np.ascontiguousarray(directions[start : start + chunk])
            outs.append(self._timed("renderer", "renderer", feeds))
        return tuple(np.concatenate([o[i] for o in outs]) for i in range(3))

    def render_view(self, images: np.ndarray, cameras: list[Camera], target: Camera, near: float, far: float,
                    background=(0.0, 0.0, 0.0), chunk: int = DEFAULT_CHUNK) -> Rendering:
        self.timings = {}
        scene = self.encode_scene(images, cameras, near, far, background)
        return self.render_target(scene, target, near, far, background, chunk)

    def render_target(self, scene: dict, target: Camera, near: float, far: float, background=(0.0, 0.0, 0.0),
                      chunk: int = DEFAULT_CHUNK) -> Rendering:
        """One target view of an encoded scene (what a cached scene costs per view)."""
        origins, directions = cams.target_rays(target)
        depth_range = (near, far)
        if self.cfg.depth_norm == "image_minmax" and "depth_range" in self.renderer_inputs:
            _, depth, _ = self.render_rays(scene, origins, directions, near, far, depth_range, chunk)
            depth_range = (float(depth.min()), float(depth.max()))
        rgb, depth, opacity = self.render_rays(scene, origins, directions, near, far, depth_range, chunk)
        rgb = rgb + (1.0 - opacity[:, None]) * np.asarray(background, dtype=np.float32)
        shape = (target.height, target.width)
        return Rendering(rgb.reshape(*shape, 3), depth.reshape(shape), opacity.reshape(shape))
