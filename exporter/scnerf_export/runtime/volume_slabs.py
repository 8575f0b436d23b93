"""The encoding volume in ONNX Runtime, as the server builds it: ``cost_slab.onnx`` over slabs of
depth planes (each run warps only its slab's planes), their first convolutions concatenated, then
``volume_net.onnx`` (G2 with the whole volume's norm statistics). A bundle written before the
volume was split has one ``volume.onnx`` instead: :func:`build_volume` runs whichever the bundle has.
"""

from __future__ import annotations

from pathlib import Path

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


def volume_by_slabs(
    cost_slab: ort.InferenceSession, volume_net: ort.InferenceSession, inputs: dict[str, np.ndarray], step: int
) -> np.ndarray:
    """The encoding volume from the volume's ``inputs``, ``step`` planes per cost slab run."""
    d = inputs["depth_planes"].shape[0]
    slabs = [cost_slab.run(None, slab_feeds(inputs, a, min(a + step, d)))[0] for a in range(0, d, step)]
    return volume_net.run(None, {"conv0": np.concatenate(slabs, axis=2)})[0]


def slab_volume_error(
    reference: np.ndarray, bundle_dir: Path, inputs: dict[str, np.ndarray], slab_sizes=(1, 5, 64)
) -> float:
    """Largest difference from ``reference`` of the volume that ``bundle_dir``'s slab graphs build
    from ``inputs``, over slabs of each size in ``slab_sizes``."""
    cost_slab, volume_net = (
        ort.InferenceSession(str(bundle_dir / f"{name}.onnx"), providers=["CPUExecutionProvider"])
        for name in ("cost_slab", "volume_net")
    )
    return max(
        float(np.abs(volume_by_slabs(cost_slab, volume_net, inputs, step) - reference).max()) for step in slab_sizes
    )


def build_volume(
    sessions: dict[str, ort.InferenceSession], inputs: dict[str, np.ndarray], pad: int, budget: int = SLAB_BUDGET_BYTES
) -> np.ndarray:
    """The encoding volume from the volume's ``inputs``, by the bundle's own graphs (``sessions``
    by graph name), slabs of what ``budget`` allows."""
    if "volume" in sessions:
        return sessions["volume"].run(None, inputs)[0]
    _, _, h, w = inputs["features"].shape
    step = planes_per_slab(inputs["depth_planes"].shape[0], (h + 2 * pad) * (w + 2 * pad), budget)
    return volume_by_slabs(sessions["cost_slab"], sessions["volume_net"], inputs, step)
