"""manifest.json, the bundle's description of itself (docs/bundle.md), as typed objects: read and
written without torch, so that running a bundle does not load the training stack.

The server reads the same file into ``Manifest`` of server/src/bundle/manifest.rs, and this module takes
serde's rules from there, so that the two accept the same files:

* keys serde ignores (unknown keys of the manifest, a graph or a tensor) are kept in ``extra`` and
  written back, so a tool that rewrites a manifest (quantize, add-guided, split-volume) never drops
  what another wrote;
* ``guided`` and ``band`` deny unknown keys (``deny_unknown_fields``), and every key of them is
  required;
* ``provenance`` is free JSON to the server; the keys the exporter reads are typed here, the rest
  kept in ``Provenance.extra``.

``config`` is stricter than the server's, which reads only what it needs: it is the exporter's
``ModelConfig`` with every key present, since a key left out would silently become the paper's
default and describe another network than the graphs.

``Manifest.load(dir).save(dir)`` writes the file it read, byte for byte, for manifests in the
order this module writes (every committed one).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..config import ModelConfig

FORMAT_VERSION = 1
FLOAT32 = "fp32"
# ``band.fill``: which views' bands take their sources' colour (runtime/band.py). Views the network
# renders dark (the default when ``band`` is absent), or every view: a network refined on a capture
# renders its band brighter than the default does, yet further from the photos than its sources.
BAND_RULES = ("when_dark", "always")


class ManifestError(ValueError):
    """A manifest.json that does not describe a bundle; the message names the key at fault."""


def model_id(variant: str, graph_sha256: dict[str, str]) -> str:
    """A bundle's id: its variant and the start of a sha256 over every graph's name and sha256, in
    the names' order, one ``name=sha256`` line each (docs/bundle.md): a bundle any of whose graphs
    changed is a new model. The server derives it the same way (``server/src/bundle/validate.rs``)."""
    listing = "".join(f"{name}={sha}\n" for name, sha in sorted(graph_sha256.items()))
    return f"scnerf-{variant}-{hashlib.sha256(listing.encode()).hexdigest()[:12]}"


# ------------------------------------------------------------------------------------------ reading


def _object(value: Any, where: str) -> dict:
    if not isinstance(value, dict):
        raise ManifestError(f"{where}: expected an object, got {json.dumps(value)[:40]}")
    return value


def _typed(value: Any, kinds: type | tuple[type, ...], where: str) -> Any:
    kinds = kinds if isinstance(kinds, tuple) else (kinds,)
    # true and false are ints to Python, never to serde.
    if not isinstance(value, kinds) or (isinstance(value, bool) and bool not in kinds):
        expected = " or ".join(k.__name__ for k in kinds)
        raise ManifestError(f"{where}: expected {expected}, got {json.dumps(value)[:40]}")
    return value


def _list(value: Any, where: str) -> list:
    return _typed(value, list, where)


def _at(where: str, key: str) -> str:
    return f"{where}.{key}" if where else key


def _require(data: dict, keys: list[str], where: str) -> None:
    missing = [key for key in keys if key not in data]
    if missing:
        raise ManifestError(f"missing {', '.join(_at(where, key) for key in missing)}")


def _keys(cls: type, data: Any, where: str, open_keys: bool = True) -> tuple[dict, dict]:
    """``data``'s values of the fields of the dataclass ``cls`` and the keys it has no field for.
    A field without a default must be there; unknown keys are an error unless ``open_keys``."""
    data = _object(data, where or "manifest")
    declared = [f for f in dataclasses.fields(cls) if f.name != "extra"]
    no_default = dataclasses.MISSING
    _require(data, [f.name for f in declared if f.default is no_default and f.default_factory is no_default], where)
    names = {f.name for f in declared}
    unknown = {k: v for k, v in data.items() if k not in names}
    if unknown and not open_keys:
        raise ManifestError(f"{where}: unknown {', '.join(sorted(unknown))} (known: {', '.join(sorted(names))})")
    return {k: v for k, v in data.items() if k in names}, unknown


# ------------------------------------------------------------------------------------------ objects


@dataclass
class TensorSpec:
    """A graph input or output: shapes list integers for fixed axes, names for dynamic ones."""

    name: str
    shape: list[int | str]
    dtype: str
    extra: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def from_json(cls, data: Any, where: str) -> TensorSpec:
        values, extra = _keys(cls, data, where)
        for i, axis in enumerate(_list(values["shape"], f"{where}.shape")):
            _typed(axis, (int, str), f"{where}.shape[{i}]")
        return cls(
            name=_typed(values["name"], str, f"{where}.name"),
            shape=list(values["shape"]),
            dtype=_typed(values["dtype"], str, f"{where}.dtype"),
            extra=extra,
        )

    def to_json(self) -> dict:
        return {"name": self.name, "shape": list(self.shape), "dtype": self.dtype, **self.extra}


def tensor_specs(names_shapes: dict[str, list]) -> list[TensorSpec]:
    """float32 tensors of these names and shapes, in order."""
    return [TensorSpec(name, list(shape), "float32") for name, shape in names_shapes.items()]


@dataclass
class GraphEntry:
    """One ONNX graph of the bundle: its file (relative to the bundle), sha256 and signature."""

    file: str
    sha256: str
    inputs: list[TensorSpec]
    outputs: list[TensorSpec]
    extra: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def from_json(cls, data: Any, where: str) -> GraphEntry:
        values, extra = _keys(cls, data, where)

        def specs(key: str) -> list[TensorSpec]:
            items = _list(values[key], f"{where}.{key}")
            return [TensorSpec.from_json(t, f"{where}.{key}[{i}]") for i, t in enumerate(items)]

        return cls(
            file=_typed(values["file"], str, f"{where}.file"),
            sha256=_typed(values["sha256"], str, f"{where}.sha256"),
            inputs=specs("inputs"),
            outputs=specs("outputs"),
            extra=extra,
        )

    def to_json(self) -> dict:
        return {
            "file": self.file,
            "sha256": self.sha256,
            "inputs": [t.to_json() for t in self.inputs],
            "outputs": [t.to_json() for t in self.outputs],
            **self.extra,
        }

    def input_names(self) -> list[str]:
        return [t.name for t in self.inputs]


@dataclass(frozen=True)
class GuidedPolicy:
    """The manifest's ``guided`` object: guided sampling's policy (docs/bundle.md; the algorithm is
    runtime/guided.py)."""

    step: int = 8
    samples: tuple[int, ...] = (32, 16, 16)
    support_threshold: float = 1e-3
    smooth_tolerance: float = 0.015
    smooth_max_step: int = 1
    # A K-sample pixel that disagrees with its neighbours by more than this is rendered again at
    # all S samples, at most ``verify_share`` of a level's, the worst first (None: never).
    verify_tolerance: float | None = 0.1
    verify_share: float | None = 0.1
    # A pixel whose neighbours' colours span more than ``edge_span`` in a channel runs at
    # ``edge_samples`` samples where its level's count is lower (None: at the level's count).
    edge_span: float | None = 0.2
    edge_samples: int | None = 32
    # Off an edge, a pixel runs at its neighbours' support rounded up to a multiple of
    # ``SAMPLE_QUANTUM``, at least this, at most its level's count (None: at the level's count).
    min_samples: int | None = 8
    # Samples of a pixel rendered again: its neighbours' support and the rest spread (None: all S).
    verify_samples: int | None = 64

    # Keys a manifest may leave out (bundles written before them): the server reads them as absent.
    OPTIONAL = ("verify_tolerance", "verify_share", "edge_span", "edge_samples", "min_samples", "verify_samples")

    def __post_init__(self) -> None:
        if self.step < 1 or self.step & (self.step - 1):
            raise ValueError(f"guided.step must be a power of two, got {self.step}")
        if len(self.samples) != self.step.bit_length() - 1:
            raise ValueError(f"guided.samples needs one count per level below step {self.step}")
        if (self.verify_tolerance is None) != (self.verify_share is None):
            raise ValueError("guided.verify_tolerance and guided.verify_share come together")
        if (self.edge_span is None) != (self.edge_samples is None):
            raise ValueError("guided.edge_span and guided.edge_samples come together")
        if any(k is not None and k < 1 for k in (self.min_samples, self.verify_samples)):
            raise ValueError("guided.min_samples and guided.verify_samples must be at least 1")

    @staticmethod
    def for_model(cfg: ModelConfig) -> GuidedPolicy:
        """The default policy for a model of ``cfg.samples`` samples per ray: no count above S,
        and a pixel rendered again at no more than half of them."""
        default = GuidedPolicy()

        def at_most(k: int | None, most: int) -> int | None:
            return None if k is None else max(1, min(k, most))

        return GuidedPolicy(
            samples=tuple(min(k, cfg.samples) for k in default.samples),
            edge_samples=at_most(default.edge_samples, cfg.samples),
            min_samples=at_most(default.min_samples, cfg.samples),
            verify_samples=at_most(default.verify_samples, cfg.samples // 2),
        )

    @classmethod
    def from_json(cls, data: Any, where: str = "guided") -> GuidedPolicy:
        # Every key but the optional ones, and no other: the server denies unknown keys.
        required = [f.name for f in dataclasses.fields(cls) if f.name not in cls.OPTIONAL]
        _require(_object(data, where), required, where)
        values, _ = _keys(cls, data, where, open_keys=False)
        samples = _list(values["samples"], f"{where}.samples")

        def optional(key: str, kind=(int, float)) -> int | float | None:
            return None if values.get(key) is None else _typed(values[key], kind, f"{where}.{key}")

        try:
            return cls(
                step=_typed(values["step"], int, f"{where}.step"),
                samples=tuple(_typed(k, int, f"{where}.samples[{i}]") for i, k in enumerate(samples)),
                support_threshold=_typed(values["support_threshold"], (int, float), f"{where}.support_threshold"),
                smooth_tolerance=_typed(values["smooth_tolerance"], (int, float), f"{where}.smooth_tolerance"),
                smooth_max_step=_typed(values["smooth_max_step"], int, f"{where}.smooth_max_step"),
                verify_tolerance=optional("verify_tolerance"),
                verify_share=optional("verify_share"),
                edge_span=optional("edge_span"),
                edge_samples=optional("edge_samples", int),
                min_samples=optional("min_samples", int),
                verify_samples=optional("verify_samples", int),
            )
        except ValueError as exc:
            raise ManifestError(str(exc)) from None

    def to_json(self) -> dict:
        written = {k: v for k, v in dataclasses.asdict(self).items() if v is not None or k not in self.OPTIONAL}
        return {**written, "samples": list(self.samples)}

    def most_reruns(self, fine: int) -> int:
        """The most pixels of a level of ``fine`` K-sample pixels rendered again (the server's
        ``GuidedPolicy::most_reruns``)."""
        return 0 if self.verify_share is None else math.floor(self.verify_share * fine)

    def rerun_samples(self, samples: int) -> int:
        """Samples of a pixel rendered again, of a model of ``samples`` per ray (the server's
        ``GuidedPolicy::rerun_samples``)."""
        return samples if self.verify_samples is None else min(self.verify_samples, samples)

    def levels(self) -> list[tuple[int, int]]:
        """(grid spacing, samples per pixel) of every level after the first, coarse to fine."""
        return [(self.step >> (i + 1), k) for i, k in enumerate(self.samples)]


# Sections a tool adds to the provenance of a bundle it rewrites, in the order they are written.
TOOL_RECORDS = ("reexport", "volume_split", "guided_graphs", "quantization", "refinement")


@dataclass
class Provenance:
    """Where the bundle's weights come from and what made its graphs. The first eight keys are
    written by every export; ``metrics``, ``source_checkpoint`` and ``source_sha256`` may be null.
    The other typed keys are written when known; ``training`` always (null when unknown)."""

    exporter_version: str
    torch_version: str
    opset: int
    created: str
    export_validation_max_abs_error: dict[str, float]
    metrics: dict | None
    source_checkpoint: str | None
    source_sha256: str | None
    source_kind: str | None = None
    training: str | dict | None = None
    derived_from: dict | None = None  # the weights a trained model started from (licence included)
    reexport: dict | None = None
    volume_split: dict | None = None
    guided_graphs: dict | None = None
    quantization: dict | None = None
    refinement: dict | None = None  # `scnerf-export refine`: the base model, the capture, the held-out scores
    extra: dict[str, Any] = field(default_factory=dict)  # e.g. the public weights' licence

    @classmethod
    def from_json(cls, data: Any, where: str = "provenance") -> Provenance:
        values, extra = _keys(cls, data, where)
        for key in ("export_validation_max_abs_error", "derived_from", *TOOL_RECORDS):
            if values.get(key) is not None:
                _object(values[key], f"{where}.{key}")
        return cls(**values, extra=extra)

    def to_json(self) -> dict:
        out = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name != "extra"}
        kept_when_null = {"metrics", "source_checkpoint", "source_sha256", "training"}
        return {**{k: v for k, v in out.items() if v is not None or k in kept_when_null}, **self.extra}


@dataclass
class Manifest:
    """manifest.json. ``graphs`` in the bundle's pipeline order; ``guided`` is there exactly when
    the guided graphs are; ``precision`` is written only for reduced-precision bundles."""

    format_version: int
    model_id: str
    variant: str
    config: ModelConfig
    graphs: dict[str, GraphEntry]
    provenance: Provenance
    guided: GuidedPolicy | None = None
    band: str = BAND_RULES[0]  # band.fill
    precision: str = FLOAT32
    extra: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def load(cls, bundle_dir: str | Path) -> Manifest:
        path = Path(bundle_dir) / "manifest.json"
        try:
            data = json.loads(path.read_text())
        except json.JSONDecodeError as exc:
            raise ManifestError(f"{path}: not JSON ({exc})") from None
        try:
            return cls.from_json(data)
        except ManifestError as exc:
            raise ManifestError(f"{path}: {exc}") from None

    @classmethod
    def from_json(cls, data: Any) -> Manifest:
        values, extra = _keys(cls, data, "")
        version = _typed(values["format_version"], int, "format_version")
        if version != FORMAT_VERSION:
            raise ManifestError(f"format_version is {version}, this exporter reads format_version {FORMAT_VERSION}")
        graphs = _object(values["graphs"], "graphs")
        guided = values.get("guided")
        band = values.get("band")
        return cls(
            format_version=version,
            model_id=_typed(values["model_id"], str, "model_id"),
            variant=_typed(values["variant"], str, "variant"),
            config=model_config(values["config"]),
            graphs={name: GraphEntry.from_json(g, f"graphs.{name}") for name, g in graphs.items()},
            provenance=Provenance.from_json(values["provenance"]),
            guided=None if guided is None else GuidedPolicy.from_json(guided),
            band=BAND_RULES[0] if band is None else band_rule(band),
            precision=_typed(values.get("precision", FLOAT32), str, "precision"),
            extra=extra,
        )

    def to_json(self) -> dict:
        out = {
            "format_version": self.format_version,
            "model_id": self.model_id,
            "variant": self.variant,
            "config": self.config.to_dict(),
            "graphs": {name: g.to_json() for name, g in self.graphs.items()},
            "provenance": self.provenance.to_json(),
        }
        if self.guided is not None:
            out["guided"] = self.guided.to_json()
        if self.band != BAND_RULES[0]:
            out["band"] = {"fill": self.band}
        if self.precision != FLOAT32:
            out["precision"] = self.precision
        return {**out, **self.extra}

    def text(self) -> str:
        return json.dumps(self.to_json(), indent=2) + "\n"

    def save(self, bundle_dir: str | Path) -> None:
        (Path(bundle_dir) / "manifest.json").write_text(self.text())

    def graph_path(self, bundle_dir: str | Path, name: str) -> Path:
        """The file of graph ``name`` in the bundle at ``bundle_dir``."""
        return Path(bundle_dir) / self.graphs[name].file

    def expected_model_id(self) -> str:
        """The id this manifest's variant and graphs give (what ``model_id`` must say)."""
        return model_id(self.variant, {name: entry.sha256 for name, entry in self.graphs.items()})


def band_rule(data: Any, where: str = "band") -> str:
    """The manifest's ``band``: ``{"fill": rule}``, one of BAND_RULES."""
    _require(_object(data, where), ["fill"], where)
    unknown = sorted(set(data) - {"fill"})
    if unknown:
        raise ManifestError(f"{where}: unknown key {unknown[0]!r}")
    fill = _typed(data["fill"], str, _at(where, "fill"))
    if fill not in BAND_RULES:
        raise ManifestError(f"{_at(where, 'fill')}: {fill!r} is not one of {', '.join(BAND_RULES)}")
    return fill


def model_config(data: Any, where: str = "config") -> ModelConfig:
    """The manifest's ``config``: every key of ModelConfig (see the module's doc), no other."""
    _require(_object(data, where), [f.name for f in dataclasses.fields(ModelConfig)], where)
    try:
        return ModelConfig.from_dict(data)
    except (TypeError, ValueError) as exc:
        raise ManifestError(f"{where}: {exc}") from None
