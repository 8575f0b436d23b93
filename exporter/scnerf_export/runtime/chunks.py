"""Rays per renderer run, the server's chunk policy mirrored for the Python runs that stand in for it
(the ONNX Runtime pipeline, eval, the benchmark). server/src/pipeline/chunks.rs is the source of
these constants and of the rule (ChunkPolicy::rays_per_chunk): change them there first.

The renderer's memory grows with rays x samples, so a memory budget bounds the rays of a run; a
cap keeps runs small enough to stay in cache. Rays are independent in the renderer graph, so the
outputs do not depend on the chunk."""

from __future__ import annotations

BYTES_PER_SAMPLE = 18 * 1024  # peak renderer activations per sample point, measured at paper size
DEFAULT_MAX_RAYS = 512  # --max-rays-per-chunk
DEFAULT_MEMORY_MB = 1024  # --chunk-memory-mb


def rays_per_run(samples: int, memory_mb: int = DEFAULT_MEMORY_MB, max_rays: int = DEFAULT_MAX_RAYS) -> int:
    """min(max_rays, budget / (samples x BYTES_PER_SAMPLE)), at least one ray."""
    by_memory = (memory_mb << 20) // (max(samples, 1) * BYTES_PER_SAMPLE)
    return min(max(by_memory, 1), max(max_rays, 1))


# Per ray of a fine run (guided sampling) beside its samples: its guide ray's rectifier heads,
# gathered (h*d_k x C floats per rectifier, twice over); paper size, both rectifiers.
GUIDED_BYTES_PER_RAY = 64 * 1024


def fine_rays_per_run(
    samples_per_ray: int, full_samples: int, memory_mb: int = DEFAULT_MEMORY_MB, max_rays: int = DEFAULT_MAX_RAYS
) -> int:
    """Rays of a fine run of ``samples_per_ray`` samples each: as many points as a full run's cap
    (max_rays x full_samples), within the memory budget, at least one ray."""
    per_ray = max(samples_per_ray, 1) * BYTES_PER_SAMPLE + GUIDED_BYTES_PER_RAY
    cap = max(max_rays, 1) * full_samples // max(samples_per_ray, 1)
    return min(max((memory_mb << 20) // per_ray, 1), max(cap, 1))
