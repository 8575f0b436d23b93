"""manifest.json, the bundle's description of itself (docs/bundle.md): read and written without
torch, so that running a bundle does not load the training stack."""

from __future__ import annotations

import json
from pathlib import Path


def write_manifest(bundle_dir: Path, manifest: dict) -> None:
    (Path(bundle_dir) / "manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")


def read_manifest(bundle_dir: str | Path) -> dict:
    return json.loads((Path(bundle_dir) / "manifest.json").read_text())
