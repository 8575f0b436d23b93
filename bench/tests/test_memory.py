"""bench.memory: the table and the estimate's fixture rows from the measured rows."""

import json
import shutil

from bench import REPO
from bench.memory import table, update_fixture

# A bundle whose volume graphs build the volume slab by slab.
SLABS_BUNDLE = REPO / "tests" / "fixtures" / "parity-slabs"


def row(bundle, sources, peak, status=200):
    return {
        "bundle": str(bundle),
        "model_id": "scnerf-mvsnerf-abc",
        "sources": sources,
        "views": 3,
        "target": "80x64",
        "status": status,
        "watchdog_stopped": False,
        "at_rest": {"rss_mib": 90.0},
        "stages": {
            "cost_slab": {"peak_mib": peak - 10, "after_mib": 200.0},
            "volume_net": {"peak_mib": peak, "after_mib": 300.0},
        },
        "after_request": {"rss_mib": 330.0},
        "request_peak_mib": peak,
    }


def test_fixture_rows_are_the_peak_above_rest_per_bundle_build_and_size(tmp_path):
    bundle = tmp_path / "b"
    bundle.mkdir()
    shutil.copyfile(SLABS_BUNDLE / "manifest.json", bundle / "manifest.json")
    fixture = tmp_path / "measured.json"
    update_fixture(fixture, [row(bundle, "640x512", 1090.0), row(bundle, "800x800", 0.0, status=503)])
    update_fixture(fixture, [row(bundle, "640x512", 1100.0)])  # measured again: replaces the row
    got = json.loads(fixture.read_text())
    config = json.loads((SLABS_BUNDLE / "manifest.json").read_text())["config"]
    assert got["bundles"] == {"scnerf-mvsnerf-abc": {"config": config}}
    assert got["rows"] == [
        {
            "bundle": "scnerf-mvsnerf-abc",
            "build": "slabs",
            "sources": [640, 512],
            "views": 3,
            "target": [80, 64],
            "peak_above_rest_mib": 1010.0,
        }
    ]
    # A scene's upload (no target) is a row of its own.
    upload = {**row(bundle, "640x512", 400.0, status=201), "views": 16, "target": None}
    update_fixture(fixture, [upload])
    rows = json.loads(fixture.read_text())["rows"]
    got = [(r["views"], r["target"], r["peak_above_rest_mib"]) for r in rows]
    assert got == [(3, [80, 64], 1010.0), (16, [0, 0], 310.0)]
    text = table([row(bundle, "640x512", 1100.0)])
    assert "| cost_slab peak / after | volume_net peak / after |" in text and "| 1090 / 200 | 1100 / 300 |" in text
