"""`scnerf-export fixtures` writes the committed parity fixtures again: tests/fixtures/parity and
its -slabs and -sweep siblings, the same files with the same graphs."""

import json
import math

import numpy as np
import pytest

from scnerf_export.cli import main
from scnerf_export.export.fixtures import split_siblings

# Measured on the machine that writes them (ONNX Runtime against PyTorch): not the fixtures' content.
MEASURED = ("error", "difference")


def files(folder):
    return sorted(p.relative_to(folder) for p in folder.rglob("*") if p.is_file())


def content(value):
    """A JSON value without the measured agreements of its graphs."""
    if isinstance(value, dict):
        return {k: content(v) for k, v in value.items() if not any(m in k for m in MEASURED)}
    if isinstance(value, list):
        return [content(v) for v in value]
    return value


def close(fresh, committed, where=""):
    """The JSON values are the same, their floats within float32 rounding."""
    if isinstance(committed, dict):
        assert isinstance(fresh, dict) and fresh.keys() == committed.keys(), where
        for k in committed:
            close(fresh[k], committed[k], f"{where}.{k}")
    elif isinstance(committed, list):
        assert isinstance(fresh, list) and len(fresh) == len(committed), where
        for i, (f, c) in enumerate(zip(fresh, committed)):
            close(f, c, f"{where}[{i}]")
    elif isinstance(committed, float):
        assert math.isclose(fresh, committed, rel_tol=1e-5, abs_tol=1e-6), f"{where}: {fresh} != {committed}"
    else:
        assert fresh == committed, where


@pytest.mark.slow
def test_the_generator_writes_the_committed_fixtures_again(tmp_path, parity_fixtures):
    assert main(["fixtures", "--out", str(tmp_path / "parity")]) == 0
    committed = [parity_fixtures, *split_siblings(parity_fixtures).values()]
    fresh = [tmp_path / "parity", *split_siblings(tmp_path / "parity").values()]
    for new, old in zip(fresh, committed):
        assert files(new) == files(old), old.name
        for name in files(old):
            where = f"{old.name}/{name}"
            if name.name == "manifest.json":
                new_json, old_json = (json.loads((d / name).read_text()) for d in (new, old))
                # The graphs (their hashes) and the model id are exactly the committed ones.
                assert content(new_json) == content(old_json), where
            elif name.suffix == ".json" and name.name != "request.json":
                close(json.loads((new / name).read_text()), json.loads((old / name).read_text()), where)
            elif name.suffix == ".f32":
                got, want = (np.fromfile(d / name, dtype="<f4") for d in (new, old))
                np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6, err_msg=where)
            else:  # graphs, source images, requests
                assert (new / name).read_bytes() == (old / name).read_bytes(), where
