"""manifest.json, the bundle's description of itself (docs/bundle.md): read and written without
torch, so that running a bundle does not load the training stack."""

from __future__ import annotations

import json
from pathlib import Path


def write_manifest(bundle_dir: Path, manifest: dict) -> None:
    (Path(bundle_dir) / "manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")


def read_manifest(bundle_dir: str | Path) -> dict:
    return json.loads((Path(bundle_dir) / "manifest.json").read_text())


def model_id(variant: str, renderer_sha256: str) -> str:
    """A bundle's id: its variant and the start of its renderer graph's sha256 (docs/bundle.md), so a
    changed renderer is a new model."""
    return f"scnerf-{variant}-{renderer_sha256[:12]}"
