"""A policy's bundle is the bundle with only its guided policy changed: the graphs are the same
files, keys set to null leave the policy, and the server reads it back."""

import json

from bench import REPO
from bench.policy_ab import policy_bundle
from scnerf_export.export.manifest import Manifest

PARITY_BUNDLE = REPO / "tests" / "fixtures" / "parity" / "bundle"


def test_a_policy_bundle_changes_only_the_guided_policy(tmp_path):
    unverified = {"verify_tolerance": None, "verify_share": None}
    out = policy_bundle(PARITY_BUNDLE, {"smooth_max_step": 0, **unverified}, tmp_path / "b")
    original = json.loads((PARITY_BUNDLE / "manifest.json").read_text())
    changed = json.loads((out / "manifest.json").read_text())
    kept = {k: v for k, v in original["guided"].items() if k not in unverified}
    assert "verify_tolerance" in original["guided"] and changed["guided"] == {**kept, "smooth_max_step": 0}
    assert {k: v for k, v in changed.items() if k != "guided"} == {k: v for k, v in original.items() if k != "guided"}
    for graph in original["graphs"].values():
        assert (out / graph["file"]).resolve() == (PARITY_BUNDLE / graph["file"]).resolve()
    policy = Manifest.load(out).guided
    assert policy.smooth_max_step == 0 and policy.verify_tolerance is None
