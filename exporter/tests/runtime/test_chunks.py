"""The server's chunk policy in Python gives the server's numbers: both are held to
tests/fixtures/rules/chunks.json (server/src/pipeline/chunks.rs reads it too; a change to the rule
on one side fails that side's tests; scripts/make-rule-fixtures.py rewrites it)."""

import json

import pytest

from scnerf_export.runtime import chunks

from conftest import REPO

FIXTURE = json.loads((REPO / "tests" / "fixtures" / "rules" / "chunks.json").read_text())


def test_constants_and_defaults_are_the_servers():
    assert (chunks.BYTES_PER_SAMPLE, chunks.GUIDED_BYTES_PER_RAY) == (
        FIXTURE["bytes_per_sample"],
        FIXTURE["guided_bytes_per_ray"],
    )
    assert (chunks.DEFAULT_MAX_RAYS, chunks.DEFAULT_MEMORY_MB) == (
        FIXTURE["default"]["max_rays"],
        FIXTURE["default"]["memory_mb"],
    )


@pytest.mark.parametrize("case", FIXTURE["rays_per_chunk"], ids=str)
def test_rays_per_run_follows_the_memory_budget_under_the_cap(case):
    assert chunks.rays_per_run(case["samples"], case["memory_mb"], case["max_rays"]) == case["rays"]


@pytest.mark.parametrize("case", FIXTURE["fine_rays_per_chunk"], ids=str)
def test_fine_runs_hold_a_full_runs_points_within_the_budget(case):
    got = chunks.fine_rays_per_run(case["samples"], case["full_samples"], case["memory_mb"], case["max_rays"])
    assert got == case["rays"]
