"""The graphs' I/O contract the exporter writes by is the one the server checks bundles against:
both are held to tests/fixtures/rules/graph_contract.json (server/src/bundle/tests.rs reads it
too; scripts/make-rule-fixtures.py rewrites it). And what each variant's graphs declare
(graph_signatures, the manifest's entries) is an instance of the contract."""

import json
from dataclasses import replace

import pytest

from scnerf_export.config import VARIANTS
from scnerf_export.export.bundle import graph_contract, graph_signatures
from scnerf_export.export.manifest import model_config
from scnerf_export.model.network import SCNeRF

from conftest import REPO

FIXTURE = json.loads((REPO / "tests" / "fixtures" / "rules" / "graph_contract.json").read_text())
CONFIGS = {c["name"]: c for c in FIXTURE["configs"]}


def test_the_fixture_holds_the_committed_bundles_configs():
    for case in CONFIGS.values():
        manifest = json.loads((REPO / case["bundle"] / "manifest.json").read_text())
        assert manifest["config"] == case["config"], f"{case['bundle']} changed: regenerate the fixture"


@pytest.mark.parametrize("name", CONFIGS)
def test_contract_is_the_fixtures(name):
    case = CONFIGS[name]
    assert graph_contract(model_config(case["config"])) == case["graphs"]


@pytest.mark.parametrize("name", CONFIGS)
@pytest.mark.parametrize("variant", VARIANTS)
def test_every_variants_declarations_keep_the_contract(name, variant):
    cfg = replace(model_config(CONFIGS[name]["config"]), variant=variant)
    declared = graph_signatures(SCNeRF(cfg))
    for graph, sides in CONFIGS[name]["graphs"].items():
        for side, tensors in sides.items():
            shapes = {t["name"]: t["shape"] for t in tensors}
            got = declared[graph][side]
            assert {n: shapes.get(n) for n in got} == got, f"{graph}.{side}: a name or shape the contract lacks"
            missing = [t["name"] for t in tensors if t["required"] and t["name"] not in got]
            assert not missing, f"{variant} {graph}.{side} lacks the required {missing}"
