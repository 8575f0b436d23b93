"""Every hyper-parameter of the network in one object, written verbatim into the bundle manifest."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

VARIANTS = ("mvsnerf", "scnerf", "scnerf-geometry", "scnerf-appearance")
DEPTH_NORMS = ("near_far", "image_minmax")


@dataclass(frozen=True)
class ModelConfig:
    """Sizes of G1, G2, M1..M4 and the rectifiers (docs/design.md "The network").

    Defaults are the paper's / public MVSNeRF checkpoint's sizes.
    """

    variant: str = "scnerf"
    views: int = 3
    feature_channels: int = 32  # C1, channels of F_i
    encoder_channels: tuple[int, int, int] = (8, 16, 32)
    volume_channels: int = 8  # channels of the encoding volume V
    unet_channels: tuple[int, int, int, int] = (8, 16, 32, 64)
    depth_planes: int = 128  # D sweeping planes of the cost volume
    samples: int = 128  # S points per ray; fixes the rectifiers' embedding size
    pad: int = 24  # cells added around H/4, W/4 of the volume
    image_multiple: int = 32
    width: int = 128  # width of the trunk M1 (feature tokens of the rectifiers)
    trunk_layers: int = 6
    skip_layer: int = 4  # the encoding E(x) is concatenated after this trunk layer
    position_freqs: int = 10  # E(x): 3 + 3*2*10 = 63
    direction_freqs: int = 5  # E(d): 3 + 3*2*5 = 33
    depth_freqs: int = 5  # E(D): 1 + 1*2*5 = 11
    heads: int = 4
    head_dim: int = 8  # d_k = d_v
    colour_hidden: int = 64
    activation_slope: float = 0.01  # leaky ReLU of G1/G2 (InPlaceABN's default in the reference code)
    norm_eps: float = 1e-5
    depth_norm: str = "near_far"
    # Paper-faithful mode: batch norm always normalises by the batch statistics (the three source
    # views for G1, the one volume for G2), as the public checkpoint was evaluated.
    norm_statistics: str = "batch"

    def __post_init__(self) -> None:
        if self.variant not in VARIANTS:
            raise ValueError(f"variant must be one of {VARIANTS}, got {self.variant!r}")
        if self.depth_norm not in DEPTH_NORMS:
            raise ValueError(f"depth_norm must be one of {DEPTH_NORMS}, got {self.depth_norm!r}")
        if self.norm_statistics not in ("batch", "running"):
            raise ValueError("norm_statistics must be 'batch' or 'running'")
        if self.depth_planes % 8:
            raise ValueError("depth_planes must be a multiple of 8 (three stride-2 stages of G2)")
        if self.pad % 8:
            raise ValueError("pad must be a multiple of 8 so that the padded volume fits G2")
        if self.image_multiple % 32:
            raise ValueError("image_multiple must be a multiple of 32")
        if not 0 <= self.skip_layer < self.trunk_layers - 1:
            raise ValueError(
                "skip_layer must name a trunk layer that has a layer after it "
                f"(0..{self.trunk_layers - 2}), got {self.skip_layer}"
            )

    @property
    def geometry_rectification(self) -> bool:
        return self.variant in ("scnerf", "scnerf-geometry")

    @property
    def appearance_rectification(self) -> bool:
        return self.variant in ("scnerf", "scnerf-appearance")

    @property
    def point_feature_channels(self) -> int:
        """f = [s (volume), per view (rgb, mask)] (DESIGN step 4)."""
        return self.volume_channels + 4 * self.views

    @property
    def position_embedding_channels(self) -> int:
        return 3 + 6 * self.position_freqs

    @property
    def direction_embedding_channels(self) -> int:
        return 3 + 6 * self.direction_freqs

    @property
    def depth_embedding_channels(self) -> int:
        return 1 + 2 * self.depth_freqs

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> "ModelConfig":
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = set(data) - known
        if unknown:
            raise ValueError(f"unknown model config keys: {sorted(unknown)}")
        values = {k: tuple(v) if isinstance(v, list) else v for k, v in data.items()}
        return cls(**values)

    def replace(self, **changes) -> "ModelConfig":
        return dataclasses.replace(self, **changes)


def small_config(variant: str = "scnerf") -> ModelConfig:
    """A network small enough for CPU training and for the committed parity fixtures."""
    return ModelConfig(
        variant=variant,
        encoder_channels=(8, 16, 32),
        depth_planes=32,
        samples=32,
        pad=8,
        width=64,
        colour_hidden=32,
    )
