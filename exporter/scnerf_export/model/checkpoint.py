"""Loading weights: the public MVSNeRF checkpoint and this project's own checkpoints."""

from __future__ import annotations

import hashlib
import re
import warnings
import zipfile
from pathlib import Path

import torch

from ..config import ModelConfig
from .network import SCNeRF

PROJECT_FORMAT = "scnerf-checkpoint-v1"
MVSNERF_LICENCE_FILE = "LICENSE.mvsnerf"

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
            raise CheckpointError(
                f"{path}: {key} has shape {tuple(tensor.shape)}, the model needs {tuple(expected[key].shape)}"
            )
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
        **_licence(path),
    }
    return model.eval(), provenance


def _licence(checkpoint: Path) -> dict:
    """The licence text that travels with every copy of the public weights (MIT requires it),
    read from ``LICENSE.mvsnerf`` beside the checkpoint; export writes it into the bundle."""
    text = checkpoint.with_name(MVSNERF_LICENCE_FILE)
    if not text.is_file():
        warnings.warn(f"{text} not found: the bundle will not carry the MVSNeRF licence text", stacklevel=2)
        return {"licence": None}
    return {"licence": "MIT", "licence_file": MVSNERF_LICENCE_FILE, "licence_text": text.read_text()}


def scnerf_from_mvsnerf(mvsnerf: SCNeRF) -> SCNeRF:
    """An ``scnerf`` network that renders what the ``mvsnerf`` network renders.

    - G1, G2 and M1 are copied.
    - M2 = ReLU(w2 ReLU(I F_r)): F_r >= 0 leaves the trunk through a ReLU, so ReLU(I F_r) = F_r,
      and w2 is MVSNeRF's density layer.
    - M4's first layer reads [F, E(D), E(d)]; MVSNeRF's colour hidden layer reads
      [L_f(F_r), d] = [W_f F_r + b_f, d]. Composed: the F columns are W_h[:, :C] W_f, the bias
      W_h[:, :C] b_f + b_h, and the columns of the raw d (the first three of E(d)) are MVSNeRF's
      direction columns; every other E(D)/E(d) column is zero. The output layer is copied.
    - Each rectifier returns ReLU(V + W_o heads + b): W_o = 0 and b = 0 give ReLU(V) = V (V >= 0),
      so F = F_c = F_r. The attention weights keep their random initialisation: they are what
      training on top learns, and they reach the output only through W_o.
    """
    cfg = mvsnerf.cfg
    if cfg.variant != "mvsnerf":
        raise ValueError(f"expected an mvsnerf network, got {cfg.variant!r}")
    model = SCNeRF(cfg.replace(variant="scnerf"))
    state = model.state_dict()
    source = mvsnerf.state_dict()
    for key, tensor in source.items():
        if key.startswith(("encoder.", "volume_net.", "renderer.m1.")):
            state[key] = tensor.clone()
    width = cfg.width
    state["renderer.m2.0.weight"] = torch.eye(width)
    state["renderer.m2.0.bias"] = torch.zeros(width)
    state["renderer.m2.2.weight"] = source["renderer.m2.0.weight"].clone()
    state["renderer.m2.2.bias"] = source["renderer.m2.0.bias"].clone()

    w_f, b_f = source["renderer.colour_head.feature_linear.weight"], source["renderer.colour_head.feature_linear.bias"]
    w_h, b_h = source["renderer.colour_head.hidden.weight"], source["renderer.colour_head.hidden.bias"]
    hidden = torch.zeros_like(state["renderer.colour_head.hidden.weight"])
    with torch.no_grad():
        hidden[:, :width] = (w_h[:, :width].double() @ w_f.double()).float()
        direction = width + cfg.depth_embedding_channels  # E(d) starts with the raw direction
        hidden[:, direction : direction + 3] = w_h[:, width:]
        state["renderer.colour_head.hidden.bias"] = (w_h[:, :width].double() @ b_f.double() + b_h.double()).float()
    state["renderer.colour_head.hidden.weight"] = hidden
    state["renderer.colour_head.out.weight"] = source["renderer.colour_head.out.weight"].clone()
    state["renderer.colour_head.out.bias"] = source["renderer.colour_head.out.bias"].clone()
    for rectifier in ("geometry", "appearance"):
        state[f"renderer.{rectifier}.w_o.weight"] = torch.zeros_like(state[f"renderer.{rectifier}.w_o.weight"])
        state[f"renderer.{rectifier}.w_o.bias"] = torch.zeros_like(state[f"renderer.{rectifier}.w_o.bias"])
    model.load_state_dict(state, strict=True)
    return model.eval()


def init_scnerf(mvsnerf_checkpoint: str | Path, out: str | Path, seed: int = 0) -> Path:
    """`init-scnerf`: the public MVSNeRF weights as an ``scnerf`` project checkpoint (see
    :func:`scnerf_from_mvsnerf`); ``seed`` draws the rectifiers' attention weights."""
    torch.manual_seed(seed)
    mvsnerf, provenance = load_mvsnerf(mvsnerf_checkpoint)
    model = scnerf_from_mvsnerf(mvsnerf)
    save_checkpoint(
        out,
        model,
        {
            "derived_from": base_weights(provenance),
            "training": {"steps": 0, "seed": seed, "what": "exact initialisation from the public MVSNeRF weights"},
        },
    )
    return Path(out)


def base_weights(provenance: dict) -> dict:
    """What a derived checkpoint records of the weights it started from."""
    keys = (
        "source_checkpoint",
        "source_sha256",
        "source_kind",
        "source_global_step",
        "licence",
        "licence_file",
        "licence_text",
    )
    return {k: provenance[k] for k in keys if k in provenance}


def save_checkpoint(path: str | Path, model: SCNeRF, extra: dict) -> None:
    torch.save(
        {"format": PROJECT_FORMAT, "config": model.cfg.to_dict(), "state_dict": model.state_dict(), **extra}, path
    )


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
    if data.get("derived_from"):
        provenance["derived_from"] = data["derived_from"]
    return model.eval(), provenance
