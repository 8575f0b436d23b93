"""The encoding volume in ONNX Runtime, as the server builds it: slab by slab of depth planes, each
slab's first convolution of G2 concatenated, then ``volume_net.onnx`` (G2 with the whole volume's
norm statistics), whose last step the server computes when the graph returns its parts
(:func:`volume_from_tail`). A slab's cost volume comes from the server's plane sweep (``plane_sweep``, then
``cost_conv.onnx``) or, in a bundle written before the sweep, from ``cost_slab.onnx`` itself; a
bundle written before the volume was split has one ``volume.onnx`` instead. :func:`build_volume`
runs whichever the bundle has.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np
import onnxruntime as ort

from ..config import ModelConfig
from ..model.cost_volume import slab_halo
from .plane_sweep import sweep

# Bytes of a slab run's working memory per cell of the slab (one plane of the padded feature
# grid, halo planes included), and the working memory a slab run may take. For cost_slab.onnx the
# server's rule and `--volume-slab-mb` default (pipeline::volume::SlabPolicy; measured in
# docs/results.md, "Memory at paper size"). The server convolves the plane sweep's cost a row at a
# time, without slabs; here the sweep's cost of a slab (41 channels of float32) and the graph's
# working memory bound the slab.
SLAB_BYTES_PER_CELL = {"slabs": 1024, "sweep": 512}
SLAB_BUDGET_BYTES = 512 << 20

# A plane sweep: (features, images, projections, depth_planes, plane_inside, pad) -> the cost.
Sweep = Callable[..., np.ndarray]


def volume_build(graphs) -> str:
    """How a bundle with ``graphs`` (names) builds the volume: "whole", "slabs" or "sweep"."""
    return "sweep" if "cost_conv" in graphs else "slabs" if "cost_slab" in graphs else "whole"


def planes_per_slab(build: str, depth_planes: int, cells_per_plane: int, budget: int = SLAB_BUDGET_BYTES) -> int:
    """Planes in a slab: what ``budget`` allows after the two halo planes, at least one, at most
    the volume's (as the server's ``SlabPolicy::planes_per_slab``)."""
    per_plane = SLAB_BYTES_PER_CELL[build] * max(cells_per_plane, 1)
    return int(np.clip(budget // per_plane - 2, 1, depth_planes))


def slab_feeds(
    build: str, inputs: dict[str, np.ndarray], start: int, stop: int, pad: int, plane_sweep: Sweep = sweep
) -> dict[str, np.ndarray]:
    """The slab graph's inputs for planes ``start..stop`` of the volume's ``inputs`` (features,
    images, projections, depth_planes): their cost (``plane_sweep``) for ``cost_conv``, the
    volume's inputs with the slab's planes for ``cost_slab``."""
    index, inside = slab_halo(inputs["depth_planes"].shape[0], start, stop)
    planes = inputs["depth_planes"][index]
    if build == "sweep":
        return {"cost": plane_sweep(inputs["features"], inputs["images"], inputs["projections"], planes, inside, pad)}
    return {**inputs, "depth_planes": planes, "plane_inside": inside}


def volume_from_tail(conv0: np.ndarray, outputs: dict[str, np.ndarray], slope: float) -> np.ndarray:
    """G2's last step from what ``volume_net.onnx`` returns in place of the volume, as the server
    computes it (docs/bundle.md): ``σ(conv0·skip_affine) + σ(interleave(phases)·phases_affine)``,
    σ the leaky ReLU of ``slope``, each affine map [scale; shift] per channel."""
    if not 0.0 <= slope < 1.0:
        raise ValueError(f"a leaky ReLU's slope is in [0, 1), got {slope}")
    phases = outputs["phases"]
    c = conv0.shape[1]
    _, _, d, h, w = phases.shape
    up = phases.reshape(c, 2, 2, 2, d, h, w).transpose(0, 4, 1, 5, 2, 6, 3).reshape(1, c, 2 * d, 2 * h, 2 * w)

    def activated(x: np.ndarray, affine: np.ndarray) -> np.ndarray:
        # In place, and the leaky ReLU as max(y, slope·y): the same bits as
        # where(y > 0, y, slope·y), over ten times faster.
        y = x * affine[0].reshape(1, c, 1, 1, 1)
        y += affine[1].reshape(1, c, 1, 1, 1)
        return np.maximum(y, y * np.float32(slope), out=y)

    return activated(conv0, outputs["skip_affine"]) + activated(up, outputs["phases_affine"])


def run_volume_net(session: ort.InferenceSession, conv0: np.ndarray, slope: float) -> np.ndarray:
    """The volume from G2's first convolution: ``volume_net.onnx``'s output, or the volume of the
    parts it returns."""
    names = [o.name for o in session.get_outputs()]
    outputs = dict(zip(names, session.run(None, {"conv0": conv0})))
    return outputs["volume"] if "volume" in outputs else volume_from_tail(conv0, outputs, slope)


def volume_by_slabs(
    sessions: dict[str, ort.InferenceSession],
    inputs: dict[str, np.ndarray],
    step: int,
    cfg: ModelConfig,
    plane_sweep: Sweep = sweep,
) -> np.ndarray:
    """The encoding volume from the volume's ``inputs``, ``step`` planes per slab run."""
    build = volume_build(sessions)
    slab = sessions["cost_conv" if build == "sweep" else "cost_slab"]
    d = inputs["depth_planes"].shape[0]
    feeds = (slab_feeds(build, inputs, a, min(a + step, d), cfg.pad, plane_sweep) for a in range(0, d, step))
    conv0 = np.concatenate([slab.run(None, f)[0] for f in feeds], axis=2)
    return run_volume_net(sessions["volume_net"], conv0, cfg.activation_slope)


def slab_volume_error(
    reference: np.ndarray,
    bundle_dir: Path,
    build: str,
    inputs: dict[str, np.ndarray],
    cfg: ModelConfig,
    slab_sizes=(1, 5, 64),
) -> float:
    """Largest difference from ``reference`` of the volume that ``bundle_dir``'s slab graphs of
    ``build`` build from ``inputs``, over slabs of each size in ``slab_sizes``."""
    sessions = {
        name: ort.InferenceSession(str(bundle_dir / f"{name}.onnx"), providers=["CPUExecutionProvider"])
        for name in ({"sweep": "cost_conv", "slabs": "cost_slab"}[build], "volume_net")
    }
    return max(float(np.abs(volume_by_slabs(sessions, inputs, step, cfg) - reference).max()) for step in slab_sizes)


def build_volume(
    sessions: dict[str, ort.InferenceSession],
    inputs: dict[str, np.ndarray],
    cfg: ModelConfig,
    budget: int = SLAB_BUDGET_BYTES,
    plane_sweep: Sweep = sweep,
) -> np.ndarray:
    """The encoding volume from the volume's ``inputs``, by the bundle's own graphs (``sessions``
    by graph name), slabs of what ``budget`` allows, the cost by ``plane_sweep`` (default: the
    server's arithmetic)."""
    build = volume_build(sessions)
    if build == "whole":
        return sessions["volume"].run(None, inputs)[0]
    _, _, h, w = inputs["features"].shape
    step = planes_per_slab(build, inputs["depth_planes"].shape[0], (h + 2 * cfg.pad) * (w + 2 * cfg.pad), budget)
    return volume_by_slabs(sessions, inputs, step, cfg, plane_sweep)
