"""Loading weights: the public MVSNeRF checkpoint and this project's own checkpoints."""

from __future__ import annotations

import hashlib
import re
import zipfile
from pathlib import Path

import torch

from .config import ModelConfig
from .model import SCNeRF

PROJECT_FORMAT = "scnerf-checkpoint-v1"

# Reference-code names -> ours. Encoder and U-Net keep the reference module names, so only their
# prefixes change; the NeRF MLP is renamed after the paper's symbols.
_MVSNERF_RENAMES = [
    (r"^feature\.", "encoder."),
    (r"^cost_reg_2\.", "volume_net."),
    (r"^nerf\.pts_linears\.", "renderer.m1.linears."),
    (r"^nerf\.pts_bias\.", "renderer.m1.feature_gate."),
    (r"^nerf\.alpha_linear\.", "renderer.m2.0."),
    (r"^nerf\.feature_linear\.", "renderer.colour_head.feature_linear."),
    (r"^nerf\.views_linears\.0\.", "renderer.colour_head.hidden."),
    (r"^nerf\.rgb_linear\.", "renderer.colour_head.out."),
]


class CheckpointError(ValueError):
    """A checkpoint that is not what it claims; the message is one line, fit for a CLI."""


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _read(path: Path) -> dict:
    if not path.is_file():
        raise CheckpointError(f"{path}: no such file")
    if not zipfile.is_zipfile(path):
        raise CheckpointError(f"{path}: not a PyTorch checkpoint (not a zip archive; truncated or foreign file?)")
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for corrupt archives
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise CheckpointError(f"{path}: unreadable checkpoint ({first})") from None
    if not isinstance(data, dict):
        raise CheckpointError(f"{path}: expected a dict of state dicts, found {type(data).__name__}")
    return data


def map_mvsnerf_state(data: dict, path: Path) -> dict[str, torch.Tensor]:
    missing = [k for k in ("network_mvs_state_dict", "network_fn_state_dict") if k not in data]
    if missing:
        raise CheckpointError(f"{path}: not an MVSNeRF checkpoint (missing {', '.join(missing)})")
    mapped: dict[str, torch.Tensor] = {}
    for key, tensor in {**data["network_mvs_state_dict"], **data["network_fn_state_dict"]}.items():
        for pattern, replacement in _MVSNERF_RENAMES:
            if re.match(pattern, key):
                mapped[re.sub(pattern, replacement, key)] = tensor
                break
        else:
            raise CheckpointError(f"{path}: unexpected tensor {key!r} (left over after mapping)")
    return mapped


def load_state_strict(model: SCNeRF, state: dict[str, torch.Tensor], path: Path) -> None:
    """Every tensor used, none left over, shapes checked."""
    expected = model.state_dict()
    missing = sorted(set(expected) - set(state))
    extra = sorted(set(state) - set(expected))
    if missing:
        raise CheckpointError(f"{path}: {len(missing)} tensors missing, first {missing[0]!r}")
    if extra:
        raise CheckpointError(f"{path}: {len(extra)} tensors left over, first {extra[0]!r}")
    for key, tensor in state.items():
        if tuple(tensor.shape) != tuple(expected[key].shape):
            raise CheckpointError(f"{path}: {key} has shape {tuple(tensor.shape)}, "
                                  f"the model needs {tuple(expected[key].shape)}")
    model.load_state_dict(state, strict=True)


def load_mvsnerf(path: str | Path, cfg: ModelConfig | None = None) -> tuple[SCNeRF, dict]:
    """The public MVSNeRF checkpoint on the ``mvsnerf`` variant, evaluated with batch statistics."""
    path = Path(path)
    data = _read(path)
    model = SCNeRF(cfg or ModelConfig(variant="mvsnerf"))
    load_state_strict(model, map_mvsnerf_state(data, path), path)
    provenance = {
        "source_checkpoint": path.name,
        "source_sha256": sha256_file(path),
        "source_kind": "mvsnerf-public",
        "source_global_step": int(data.get("global_step", -1)),
        "training": "public MVSNeRF checkpoint (DTU, MIT licence), imported without change",
    }
    return model.eval(), provenance


def save_checkpoint(path: str | Path, model: SCNeRF, extra: dict) -> None:
    torch.save({"format": PROJECT_FORMAT, "config": model.cfg.to_dict(),
                "state_dict": model.state_dict(), **extra}, path)


def load_checkpoint(path: str | Path) -> tuple[SCNeRF, dict]:
    """A project checkpoint (from ``train``) or the public MVSNeRF one, recognised by content."""
    path = Path(path)
    data = _read(path)
    if "network_mvs_state_dict" in data:
        return load_mvsnerf(path)
    if data.get("format") != PROJECT_FORMAT:
        raise CheckpointError(f"{path}: neither an MVSNeRF nor a {PROJECT_FORMAT} checkpoint")
    try:
        cfg = ModelConfig.from_dict(data["config"])
    except (KeyError, TypeError, ValueError) as exc:
        raise CheckpointError(f"{path}: bad model config ({exc})") from None
    model = SCNeRF(cfg)
    load_state_strict(model, data["state_dict"], path)
    provenance = {
        "source_checkpoint": path.name,
        "source_sha256": sha256_file(path),
        "source_kind": "scnerf-serve-training",
        "training": data.get("training"),
        "metrics": data.get("metrics"),
    }
    return model.eval(), provenance
