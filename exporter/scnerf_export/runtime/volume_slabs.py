"""The encoding volume in ONNX Runtime, as the server builds it: ``cost_slab.onnx`` over slabs of
depth planes (each run warps only its slab's planes), their first convolutions concatenated, then
``volume_net.onnx`` (G2 with the whole volume's norm statistics). A bundle written before the
volume was split has one ``volume.onnx`` instead: :func:`build_volume` runs whichever the bundle has.
"""

from __future__ import annotations

import numpy as np
import onnxruntime as ort

from ..model.cost_volume import slab_halo

# Bytes of the cost slab graph's working memory per cell of a slab (one plane of the padded
# feature grid, halo planes included), and the working memory a slab run may take: the server's
# rule and `--volume-slab-mb` default (pipeline::volume::SlabPolicy; measured in
# docs/results.md, "Memory at paper size").
SLAB_BYTES_PER_CELL = 1024
SLAB_BUDGET_BYTES = 512 << 20


def planes_per_slab(depth_planes: int, cells_per_plane: int, budget: int = SLAB_BUDGET_BYTES) -> int:
    """Planes in a slab: what ``budget`` allows after the two halo planes, at least one, at most
    the volume's (as the server's ``SlabPolicy::planes_per_slab``)."""
    return int(np.clip(budget // (SLAB_BYTES_PER_CELL * max(cells_per_plane, 1)) - 2, 1, depth_planes))


def slab_feeds(inputs: dict[str, np.ndarray], start: int, stop: int) -> dict[str, np.ndarray]:
    """The cost slab graph's inputs for planes ``start..stop`` of the volume's ``inputs``
    (features, images, projections, depth_planes)."""
    index, inside = slab_halo(inputs["depth_planes"].shape[0], start, stop)
    return {**inputs, "depth_planes": inputs["depth_planes"][index], "plane_inside": inside}


def build_volume(
    sessions: dict[str, ort.InferenceSession], inputs: dict[str, np.ndarray], pad: int, budget: int = SLAB_BUDGET_BYTES
) -> np.ndarray:
    """The encoding volume from the volume's ``inputs``, by the bundle's own graphs (``sessions``
    by graph name), slabs of what ``budget`` allows."""
    if "volume" in sessions:
        return sessions["volume"].run(None, inputs)[0]
    d = inputs["depth_planes"].shape[0]
    _, _, h, w = inputs["features"].shape
    step = planes_per_slab(d, (h + 2 * pad) * (w + 2 * pad), budget)
    slabs = [sessions["cost_slab"].run(None, slab_feeds(inputs, a, min(a + step, d)))[0] for a in range(0, d, step)]
    return sessions["volume_net"].run(None, {"conv0": np.concatenate(slabs, axis=2)})[0]
