"""Training/validation streams, the npz scene cache and preview contact sheets.

Seeds: training scene i has seed ``TRAIN_SEED0 + i`` (0, 1, 2, ...), validation scene i has seed
``VAL_SEED0 + i`` (10_000_000, ...).  Training pools are limited to fewer than 10 million scenes, so
the two ranges can never overlap.  Scene i uses layout ``layouts[i % len(layouts)]``, so any prefix
of either split is balanced over the layouts.
"""

from __future__ import annotations

import os
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np

from .core import ALL_LAYOUTS, LAYOUTS, Camera, Scene, View
from .scenes import GAPS, make_scene, pick_sources

TRAIN_SEED0 = 0
VAL_SEED0 = 10_000_000
CACHE_VERSION = 1


@dataclass
class Example:
    """One training example: three source views (the first is the reference) and a target view."""

    sources: list[View]
    target: View
    near: float
    far: float
    layout: str
    scene_index: int
    scene_seed: int
    target_index: int
    source_indices: list[int]
    gap: str


def split_seed(split: str, index: int) -> int:
    """Scene seed of scene ``index`` of a split; raises if a training index would reach the
    validation range."""
    if split == "train":
        if not 0 <= index < VAL_SEED0 - TRAIN_SEED0:
            raise ValueError(f"training scene index {index} out of range")
        return TRAIN_SEED0 + index
    if split == "val":
        if index < 0:
            raise ValueError(f"validation scene index {index} out of range")
        return VAL_SEED0 + index
    raise ValueError(f"split must be 'train' or 'val', got {split!r}")


def scene_filename(seed: int, layout: str, n_views: int, width: int, height: int) -> str:
    """Cache file name: everything that changes the pixels is in it, so a cache never serves a scene
    rendered with other settings."""
    return f"{layout}_{seed:08d}_{width}x{height}_v{n_views}.npz"


# ----------------------------------------------------------------------------------------------
# cache


def save_scene(scene: Scene, path: str | os.PathLike) -> None:
    """Write a scene as a compressed npz (images and alpha as uint8, which is lossless because views
    are already quantised to 8 bits; depth float32 with inf for misses)."""
    images = np.stack([v.image for v in scene.views])
    alphas = np.stack([v.alpha for v in scene.views])
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + f".tmp{os.getpid()}.npz")
    np.savez_compressed(
        tmp,
        version=np.int64(CACHE_VERSION),
        images=np.round(images * 255.0).astype(np.uint8),
        alphas=np.round(alphas * 255.0).astype(np.uint8),
        depths=np.stack([v.depth for v in scene.views]).astype(np.float32),
        K=np.stack([v.camera.K for v in scene.views]),
        w2c=np.stack([v.camera.w2c for v in scene.views]),
        near=np.float64(scene.near),
        far=np.float64(scene.far),
        layout=np.str_(scene.layout),
        seed=np.int64(scene.seed),
        supersample=np.int64(scene.meta.get("supersample", 1)),
    )
    os.replace(tmp, path)  # atomic, so parallel builders and readers never see half a file


def load_scene(path: str | os.PathLike) -> Scene:
    """Read a scene written by :func:`save_scene`; arrays equal those of the freshly rendered scene."""
    with np.load(path) as z:
        if int(z["version"]) != CACHE_VERSION:
            raise ValueError(f"{path}: cache version {int(z['version'])}, expected {CACHE_VERSION}")
        images = z["images"].astype(np.float32) / np.float32(255.0)
        alphas = z["alphas"].astype(np.float32) / np.float32(255.0)
        depths, K, w2c = z["depths"], z["K"], z["w2c"]
        n, h, w = depths.shape
        views = [
            View(
                image=images[i], depth=depths[i], alpha=alphas[i], camera=Camera(K=K[i], w2c=w2c[i], width=w, height=h)
            )
            for i in range(n)
        ]
        return Scene(
            views=views,
            near=float(z["near"]),
            far=float(z["far"]),
            layout=str(z["layout"]),
            seed=int(z["seed"]),
            meta={"supersample": int(z["supersample"])},
        )


def _build_one(args: tuple) -> str:
    path, seed, layout, n_views, width, height, supersample, overwrite = args
    if overwrite or not Path(path).exists():
        save_scene(make_scene(seed, layout, n_views, width, height, supersample), path)
    return str(path)


def build_dataset(
    out_dir: str | os.PathLike,
    n_scenes: int,
    seed0: int = TRAIN_SEED0,
    layouts: Sequence[str] = LAYOUTS,
    n_views: int = 20,
    width: int = 160,
    height: int = 128,
    supersample: int = 2,
    workers: int = 1,
    overwrite: bool = False,
) -> list[Path]:
    """Render scenes ``seed0 .. seed0 + n_scenes - 1`` (layout ``layouts[i % len(layouts)]``) into
    ``out_dir`` as npz files and return their paths; existing files are kept unless ``overwrite``.
    Use ``seed0 = VAL_SEED0`` for the validation split.  ``workers`` > 1 renders in processes."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    jobs = []
    for i in range(n_scenes):
        seed, layout = seed0 + i, layouts[i % len(layouts)]
        path = out / scene_filename(seed, layout, n_views, width, height)
        jobs.append((path, seed, layout, n_views, width, height, supersample, overwrite))
    if workers > 1:
        import multiprocessing as mp

        with mp.get_context("spawn").Pool(workers) as pool:
            list(pool.imap_unordered(_build_one, jobs))
    else:
        for job in jobs:
            _build_one(job)
    return [job[0] for job in jobs]


# ----------------------------------------------------------------------------------------------
# streams


class ProceduralDataset:
    """A pool of procedural scenes of one split and a seeded stream of examples drawn from it.

    ``scene(i)`` reads the npz cache in ``cache_dir`` when it holds the scene (writing it there after
    rendering otherwise), and keeps the last ``memory_scenes`` scenes in memory.  Rendering a 20-view
    160x128 scene takes a few seconds, so build the cache first (:func:`build_dataset`, or
    :meth:`prefetch`) for training.

    Iterating yields an endless, seeded stream of :class:`Example`: a random scene, a random target
    view, and its sources for a gap drawn from ``gaps``.  :meth:`fixed_examples` gives the
    deterministic examples used for validation tables.
    """

    def __init__(
        self,
        split: str = "train",
        n_scenes: int = 96,
        layouts: Sequence[str] = LAYOUTS,
        n_views: int = 20,
        width: int = 160,
        height: int = 128,
        gaps: Sequence[str] = ("small",),
        n_sources: int = 3,
        cache_dir: str | os.PathLike | None = None,
        supersample: int = 2,
        seed: int = 0,
        memory_scenes: int = 16,
    ):
        for layout in layouts:
            if layout not in ALL_LAYOUTS:
                raise ValueError(f"unknown layout {layout!r}")
        for gap in gaps:
            if gap not in GAPS:
                raise ValueError(f"unknown gap {gap!r}")
        split_seed(split, max(n_scenes - 1, 0))  # validates the split and the pool size
        self.split, self.n_scenes, self.layouts = split, n_scenes, tuple(layouts)
        self.n_views, self.width, self.height = n_views, width, height
        self.gaps, self.n_sources, self.supersample = tuple(gaps), n_sources, supersample
        self.cache_dir = Path(cache_dir) if cache_dir is not None else None
        self.seed, self.memory_scenes = seed, memory_scenes
        self._memory: OrderedDict[int, Scene] = OrderedDict()

    def __len__(self) -> int:
        return self.n_scenes

    def scene_info(self, index: int) -> tuple[int, str]:
        """(seed, layout) of scene ``index``."""
        return split_seed(self.split, index), self.layouts[index % len(self.layouts)]

    def scene_path(self, index: int) -> Path | None:
        if self.cache_dir is None:
            return None
        seed, layout = self.scene_info(index)
        return self.cache_dir / scene_filename(seed, layout, self.n_views, self.width, self.height)

    def scene(self, index: int) -> Scene:
        if index in self._memory:
            self._memory.move_to_end(index)
            return self._memory[index]
        seed, layout = self.scene_info(index)
        path = self.scene_path(index)
        if path is not None and path.exists():
            scene = load_scene(path)
        else:
            scene = make_scene(seed, layout, self.n_views, self.width, self.height, self.supersample)
            if path is not None:
                save_scene(scene, path)
        self._memory[index] = scene
        while len(self._memory) > self.memory_scenes:
            self._memory.popitem(last=False)
        return scene

    def prefetch(self, workers: int = 1) -> list[Path]:
        """Render every scene of the pool into ``cache_dir``."""
        if self.cache_dir is None:
            raise ValueError("prefetch needs a cache_dir")
        seed0 = split_seed(self.split, 0)
        return build_dataset(
            self.cache_dir,
            self.n_scenes,
            seed0,
            self.layouts,
            self.n_views,
            self.width,
            self.height,
            self.supersample,
            workers,
        )

    def example(self, index: int, target_index: int, gap: str) -> Example:
        scene = self.scene(index)
        src = pick_sources(scene, target_index, gap, self.n_sources)
        return Example(
            sources=[scene.views[i] for i in src],
            target=scene.views[target_index],
            near=scene.near,
            far=scene.far,
            layout=scene.layout,
            scene_index=index,
            scene_seed=scene.seed,
            target_index=target_index,
            source_indices=src,
            gap=gap,
        )

    def sample(self, rng: np.random.Generator) -> Example:
        index = int(rng.integers(self.n_scenes))
        target = int(rng.integers(self.n_views))
        gap = self.gaps[int(rng.integers(len(self.gaps)))]
        return self.example(index, target, gap)

    def __iter__(self) -> Iterator[Example]:
        rng = np.random.default_rng(self.seed)
        while True:
            yield self.sample(rng)

    def fixed_examples(self, targets_per_scene: int = 1, gaps: Sequence[str] | None = None) -> Iterator[Example]:
        """Deterministic examples: for every scene, ``targets_per_scene`` target views (drawn from
        the scene's seed) under every gap in ``gaps`` (default: this dataset's gaps)."""
        for index in range(self.n_scenes):
            seed, _ = self.scene_info(index)
            rng = np.random.default_rng([seed, 7])
            targets = rng.choice(self.n_views, size=min(targets_per_scene, self.n_views), replace=False)
            for target in targets:
                for gap in gaps or self.gaps:
                    yield self.example(index, int(target), gap)


# ----------------------------------------------------------------------------------------------
# preview


def _inverse_depth_colors(depth: np.ndarray, near: float, far: float) -> np.ndarray:
    """Inverse depth mapped to a blue (far) - yellow (near) ramp; empty pixels black."""
    with np.errstate(divide="ignore"):
        inv = (1.0 / depth - 1.0 / far) / (1.0 / near - 1.0 / far)
    t = np.clip(np.nan_to_num(inv, nan=0.0, posinf=0.0, neginf=0.0), 0.0, 1.0)[..., None]
    lo, mid, hi = np.array([0.05, 0.05, 0.35]), np.array([0.8, 0.25, 0.4]), np.array([1.0, 0.95, 0.3])
    rgb = np.where(t < 0.5, lo + (mid - lo) * (2 * t), mid + (hi - mid) * (2 * t - 1))
    return np.where(np.isfinite(depth)[..., None], rgb, 0.0)


def save_preview(scene: Scene, path: str | os.PathLike, max_views: int = 8) -> None:
    """PNG contact sheet: up to ``max_views`` evenly spread views, rgb above their inverse depth."""
    from PIL import Image

    idx = np.unique(np.linspace(0, len(scene.views) - 1, min(max_views, len(scene.views))).round().astype(int))
    h, w = scene.views[0].image.shape[:2]
    pad = 2
    sheet = np.ones((2 * h + 3 * pad, len(idx) * (w + pad) + pad, 3))
    for col, i in enumerate(idx):
        v = scene.views[i]
        x = pad + col * (w + pad)
        sheet[pad : pad + h, x : x + w] = v.image
        sheet[2 * pad + h : 2 * pad + 2 * h, x : x + w] = _inverse_depth_colors(v.depth, scene.near, scene.far)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.round(sheet * 255).astype(np.uint8)).save(path)
