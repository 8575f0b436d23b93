"""The server's chunk policy in Python gives the server's numbers (server/src/pipeline/chunks.rs)."""

from scnerf_export.runtime.chunks import rays_per_run


def test_rays_per_run_follows_the_memory_budget_under_the_cap():
    assert rays_per_run(128, memory_mb=4096, max_rays=4096) == 1820  # chunks.rs: chunk_size_from_budget
    assert rays_per_run(1, memory_mb=4096, max_rays=4096) == 4096
    assert rays_per_run(128, memory_mb=0, max_rays=4096) == 1


def test_default_policy_for_the_paper_and_the_default_bundle():
    assert rays_per_run(128) == 455  # 1 GiB / (128 x 18 KiB)
    assert rays_per_run(48) == 512  # capped by --max-rays-per-chunk
