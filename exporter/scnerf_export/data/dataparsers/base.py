"""The one type behind every scene format: a parser reads a folder (or file) into a SceneData."""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import ClassVar

from ..scene import SceneData


class DataParser(ABC):
    """A scene format on disk. ``load`` returns views whose cameras are in the canonical form, the
    scene's [near, far] and background, and the format's default source/target views if it has any."""

    format: ClassVar[str]  # the name --format takes

    @abstractmethod
    def load(
        self, path, scale: float = 1.0, background=None, near=None, far=None, ignore_distortion: bool = False
    ) -> SceneData:
        """``scale`` resizes every image (and its intrinsics); ``background`` (RGB in [0,1]) is what
        alpha is composited on; ``near``/``far`` override the format's own depth range. Photos with lens
        distortion are resampled to a pinhole camera (:mod:`..lens`), as the server sends them,
        unless ``ignore_distortion`` (then used as pinhole, with a warning)."""
