"""`scnerf-export blend-heads`: the trained heads moved part of the way back to the initialisation,
theta = theta_0 + alpha (theta_1 - theta_0), with alpha chosen on validation views.

``finetune`` selects a step by each validation scene's mean PSNR, so one view may still lose
against the initialisation (= the public MVSNeRF) while its scene gains. Along the line between
the two sets of heads each view's PSNR moves smoothly, and alpha = 0 renders exactly what MVSNeRF
renders. The chosen alpha has the best mean gain over every validation view (nearest and fixed
sources, full image and DTU's object mask) among those that keep each scene's mean under the
paper's protocol and each view of the quality table (``GUARDED``) no worse than the
initialisation; alpha = 0 if none does. Validation scenes choose alpha, never enter a gradient.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..data import datasets
from ..evaluate.eval import source_pool
from ..model.checkpoint import load_checkpoint, save_checkpoint, sha256_file
from ..model.network import SCNeRF
from .finetune import HEADS, VALIDATION, RayBank, backbone_digest, cached, score, target_bank

ALPHAS = (0.0, 0.2, 0.4, 0.5, 0.6, 0.8, 1.0)
PROTOCOLS = ("nearest", "fixed")
# The views of the quality table (docs/results.md), full image, the paper's protocol.
GUARDED = ("lego/r_28/nearest/psnr", "scan37/32/nearest/psnr")


@dataclass(frozen=True)
class ViewSpec:
    """One validation view scored the paper's way at the size the quality table renders it."""

    scene: str
    path: str
    format: str
    target: str
    protocol: str  # "nearest": the 3 nearest pool views; "fixed": the scene's fixed triple
    target_scale: float = 0.5
    stride: int = 4  # every stride-th pixel of the scaled target along each axis

    @property
    def key(self) -> str:
        return f"{self.scene}/{self.target}/{self.protocol}"


def validation_views(shared: Path) -> list[ViewSpec]:
    """The validation scenes' own targets (lego's val views, scan37's test views), each from its
    nearest and from the fixed sources."""
    views = []
    for scene in VALIDATION:
        targets = datasets.load_scene(shared / "data" / scene.path, scene.format).default_targets
        views += [
            ViewSpec(scene.name, scene.path, scene.format, target, protocol)
            for target in targets
            for protocol in PROTOCOLS
        ]
    return views


def view_bank(model: SCNeRF, shared: Path, spec: ViewSpec) -> RayBank:
    scene = datasets.load_scene(shared / "data" / spec.path, spec.format)
    if spec.protocol == "nearest":
        names = datasets.nearest_sources(scene, spec.target, source_pool(scene, scene.default_targets))
    else:
        names = scene.default_sources
    return target_bank(model, scene, spec.target, names, spec.target_scale, spec.stride)


def blended(theta_0: dict, theta_1: dict, alpha: float) -> dict:
    return {k: v + alpha * (theta_1[k] - v) if v.is_floating_point() else v for k, v in theta_0.items()}


def guards(scores: dict[str, float]) -> dict[str, float]:
    """What alpha may not make worse: each scene's mean per metric under the paper's protocol (nearest
    sources; scores are keyed scene/target/protocol/metric) and the ``GUARDED`` views."""
    means: dict[str, list[float]] = {}
    for key, value in scores.items():
        scene, _, protocol, metric = key.split("/")
        if protocol == "nearest":
            means.setdefault(f"{scene}/mean/nearest/{metric}", []).append(value)
    return {**{k: float(np.mean(v)) for k, v in means.items()}, **{k: scores[k] for k in GUARDED if k in scores}}


def choose_alpha(table: dict[float, dict[str, float]]) -> float:
    """The alpha with the best mean gain over alpha = 0 among those that lose on no guard (table:
    alpha -> scene/target/protocol/metric -> PSNR)."""
    initial, initial_guards = table[0.0], guards(table[0.0])
    best, best_gain = 0.0, 0.0
    for alpha, scores in sorted(table.items()):
        gain = float(np.mean([scores[k] - initial[k] for k in initial]))
        kept = all(value >= initial_guards[k] for k, value in guards(scores).items())
        if kept and gain > best_gain:
            best, best_gain = alpha, gain
    return best


def score_table(model: SCNeRF, theta_0: dict, theta_1: dict, banks, alphas, path: Path) -> dict:
    """PSNR per alpha and validation metric, read from ``path`` when an earlier run of the same
    checkpoints and views wrote it (scoring takes minutes per alpha on a CPU); ``banks()`` gives
    the views' ray banks, read only when an alpha is missing."""
    table = {float(a): s for a, s in json.loads(path.read_text()).items()} if path.is_file() else {}
    missing = sorted({0.0, *alphas} - set(table))
    banks = banks() if missing else {}
    for alpha in missing:
        model.load_state_dict(blended(theta_0, theta_1, alpha))
        table[alpha] = {
            f"{key}/{metric}": value for key, bank in banks.items() for metric, value in score(model, bank).items()
        }
        path.write_text(json.dumps({str(a): s for a, s in sorted(table.items())}, indent=1) + "\n")
    for alpha, scores in sorted(table.items()):
        gains = [scores[k] - table[0.0][k] for k in table[0.0]]
        print(f"alpha {alpha:.2f}: mean gain {np.mean(gains):+.3f} dB, worst view {min(gains):+.3f} dB", flush=True)
    return table


def blend_heads(
    init: str | Path,
    trained: str | Path,
    out: str | Path,
    shared: str | Path,
    cache_dir: str | Path,
    alphas: tuple[float, ...] = ALPHAS,
) -> tuple[Path, float]:
    """Write ``out``: the trained checkpoint with its heads blended toward ``init`` by the chosen alpha."""
    model, init_provenance = load_checkpoint(init)
    trained_model, provenance = load_checkpoint(trained)
    model.eval()
    theta_0 = {k: v.clone() for k, v in model.state_dict().items()}
    theta_1 = trained_model.state_dict()
    moved = sorted({k.split(".")[1] for k in theta_0 if not torch.equal(theta_0[k], theta_1[k])})
    if not set(moved) <= set(HEADS) or backbone_digest(model) != backbone_digest(trained_model):
        raise ValueError(f"{trained}: only the heads {HEADS} may differ from {init}, found {moved}")

    cache = Path(cache_dir)
    backbone = backbone_digest(model)
    specs = validation_views(Path(shared))

    def banks() -> dict[str, RayBank]:
        return {
            spec.key: cached(
                cache / f"view-{backbone}-{spec.key.replace('/', '-')}-{spec.target_scale}-{spec.stride}.pt",
                lambda spec=spec: view_bank(model, Path(shared), spec),
            )
            for spec in specs
        }

    views = json.dumps([spec.__dict__ for spec in specs])
    digest = hashlib.sha256((sha256_file(Path(init)) + sha256_file(Path(trained)) + views).encode()).hexdigest()[:12]
    table = score_table(model, theta_0, theta_1, banks, alphas, cache / f"scores-{digest}.json")
    alpha = choose_alpha(table)
    model.load_state_dict(blended(theta_0, theta_1, alpha))
    training = dict(provenance.get("training", {}))
    training["blend"] = {
        "rule": "heads theta_0 + alpha (theta_1 - theta_0) between the initialisation and the trained step; "
        "alpha with the best mean PSNR gain over every validation view (nearest and fixed sources, full "
        "image and object-masked), among those no worse than the initialisation on each scene's mean "
        f"with the nearest sources nor on {', '.join(GUARDED)} (validation scenes choose, never train)",
        "alpha": alpha,
        "views": [spec.__dict__ for spec in specs],
        "psnr": {str(a): scores for a, scores in table.items()},
    }
    path = Path(out)
    path.parent.mkdir(parents=True, exist_ok=True)
    save_checkpoint(path, model, {"derived_from": provenance.get("derived_from", init_provenance.get("derived_from")),
                                  "training": training})  # fmt: skip
    (path.parent / "blend.json").write_text(json.dumps(training["blend"], indent=1) + "\n")
    return path, alpha
