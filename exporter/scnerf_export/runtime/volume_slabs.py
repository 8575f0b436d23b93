"""The encoding volume in ONNX Runtime, as the server builds it: slab by slab of depth planes, each
slab's first convolution of G2 concatenated, then ``volume_net.onnx`` (G2 with the whole volume's
norm statistics). A slab's cost volume comes from the server's plane sweep (``plane_sweep``, then
``cost_conv.onnx``) or, in a bundle written before the sweep, from ``cost_slab.onnx`` itself; a
bundle written before the volume was split has one ``volume.onnx`` instead. :func:`build_volume`
runs whichever the bundle has.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnxruntime as ort

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


def volume_build(graphs) -> str:
    """How a bundle with ``graphs`` (names) builds the volume: "whole", "slabs" or "sweep"."""
    return "sweep" if "cost_conv" in graphs else "slabs" if "cost_slab" in graphs else "whole"


def planes_per_slab(build: str, depth_planes: int, cells_per_plane: int, budget: int = SLAB_BUDGET_BYTES) -> int:
    """Planes in a slab: what ``budget`` allows after the two halo planes, at least one, at most
    the volume's (as the server's ``SlabPolicy::planes_per_slab``)."""
    per_plane = SLAB_BYTES_PER_CELL[build] * max(cells_per_plane, 1)
    return int(np.clip(budget // per_plane - 2, 1, depth_planes))


def slab_feeds(build: str, inputs: dict[str, np.ndarray], start: int, stop: int, pad: int) -> dict[str, np.ndarray]:
    """The slab graph's inputs for planes ``start..stop`` of the volume's ``inputs`` (features,
    images, projections, depth_planes): their cost (the plane sweep) for ``cost_conv``, the
    volume's inputs with the slab's planes for ``cost_slab``."""
    index, inside = slab_halo(inputs["depth_planes"].shape[0], start, stop)
    planes = inputs["depth_planes"][index]
    if build == "sweep":
        return {"cost": sweep(inputs["features"], inputs["images"], inputs["projections"], planes, inside, pad)}
    return {**inputs, "depth_planes": planes, "plane_inside": inside}


def volume_by_slabs(
    sessions: dict[str, ort.InferenceSession], inputs: dict[str, np.ndarray], step: int, pad: int
) -> np.ndarray:
    """The encoding volume from the volume's ``inputs``, ``step`` planes per slab run."""
    build = volume_build(sessions)
    slab = sessions["cost_conv" if build == "sweep" else "cost_slab"]
    d = inputs["depth_planes"].shape[0]
    slabs = [slab.run(None, slab_feeds(build, inputs, a, min(a + step, d), pad))[0] for a in range(0, d, step)]
    return sessions["volume_net"].run(None, {"conv0": np.concatenate(slabs, axis=2)})[0]


def slab_volume_error(
    reference: np.ndarray, bundle_dir: Path, build: str, inputs: dict[str, np.ndarray], pad: int, slab_sizes=(1, 5, 64)
) -> float:
    """Largest difference from ``reference`` of the volume that ``bundle_dir``'s slab graphs of
    ``build`` build from ``inputs``, over slabs of each size in ``slab_sizes``."""
    sessions = {
        name: ort.InferenceSession(str(bundle_dir / f"{name}.onnx"), providers=["CPUExecutionProvider"])
        for name in ({"sweep": "cost_conv", "slabs": "cost_slab"}[build], "volume_net")
    }
    return max(float(np.abs(volume_by_slabs(sessions, inputs, step, pad) - reference).max()) for step in slab_sizes)


def build_volume(
    sessions: dict[str, ort.InferenceSession], inputs: dict[str, np.ndarray], pad: int, budget: int = SLAB_BUDGET_BYTES
) -> np.ndarray:
    """The encoding volume from the volume's ``inputs``, by the bundle's own graphs (``sessions``
    by graph name), slabs of what ``budget`` allows."""
    build = volume_build(sessions)
    if build == "whole":
        return sessions["volume"].run(None, inputs)[0]
    _, _, h, w = inputs["features"].shape
    step = planes_per_slab(build, inputs["depth_planes"].shape[0], (h + 2 * pad) * (w + 2 * pad), budget)
    return volume_by_slabs(sessions, inputs, step, pad)
