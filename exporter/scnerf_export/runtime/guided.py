"""Guided sampling: a view rendered coarse to fine, the network run only where the surface is.

The one description of the policy in Python (the server's is server/src/pipeline/guided/; the
two are held to each other by the parity fixtures); its numbers are the manifest's ``guided``
object, ``export.manifest.GuidedPolicy``. A view is rendered in levels of pixels on
nested grids:

* level 0, every ``step``-th pixel in both axes: the full network at the S uniform samples
  (``renderer_guide.onnx``), which also returns each ray's compositing weights and rectifier heads;
* then grids of half the spacing each, down to every pixel. A pixel of a level has neighbours
  rendered before it at one spacing in each axis (2 or 4 of them). Where their composited colours
  agree within ``smooth_tolerance`` (on grids no coarser than ``smooth_max_step``), the pixel takes
  their mean and the network does not run. Otherwise its samples come from the neighbours'
  weights (:func:`select_samples`): the K (the level's ``samples``) uniform samples where the
  neighbours composite most, each standing for the nearby samples where a neighbour saw matter
  (its multiplicity), run through ``renderer_fine.onnx`` with the rectifier heads of the nearest
  level-0 ray (:func:`nearest_guide`). Where the neighbours' colours span more than
  ``edge_span``, the pixel lies on an edge and runs at ``edge_samples`` instead. With
  ``min_samples``, a pixel whose neighbours' support spans fewer samples runs at fewer
  (:func:`samples_at`).
  Where the policy has ``verify_tolerance``, a level's K-sample pixels whose outputs disagree with
  their neighbours' (:func:`disagreeing`) are rendered again at ``verify_samples`` (all S without
  it) spread over the ray (:func:`spread_samples`, through ``renderer_fine.onnx``) before the next
  level reads them.

A level-0 pixel is rendered exactly as with full sampling.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .. import cameras as cams
from ..cameras import Camera
from ..export.manifest import GuidedPolicy
from .view import Rendering, renderer_passes

# What a guide run returns per ray: rgb (R,3), depth (R), opacity (R), weights (R,S), and per
# rectifier name its heads (R, h*d_k, C).
GuideRun = Callable[[np.ndarray, np.ndarray], dict[str, np.ndarray]]
# What a fine run takes: origins, directions, sample_index (R,K), multiplicity (R,K), each ray's
# guide ray (R) (the guide rays' heads are the caller's); returns rgb, depth, opacity, weights (R,K).
FineRun = Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray], dict[str, np.ndarray]]


def level_pixels(width: int, height: int, spacing: int) -> np.ndarray:
    """Pixels (v, u) of the grid of ``spacing`` not on the grid of twice it, row by row: the
    pixels one level renders (all of the grid for the first level's spacing, see ``first``)."""
    v, u = np.meshgrid(np.arange(0, height, spacing), np.arange(0, width, spacing), indexing="ij")
    v, u = v.ravel(), u.ravel()
    keep = (v % (2 * spacing) != 0) | (u % (2 * spacing) != 0)
    return np.stack([v[keep], u[keep]], axis=1)


def first_level_pixels(width: int, height: int, step: int) -> np.ndarray:
    v, u = np.meshgrid(np.arange(0, height, step), np.arange(0, width, step), indexing="ij")
    return np.stack([v.ravel(), u.ravel()], axis=1)


def neighbours(pixels: np.ndarray, width: int, height: int, spacing: int) -> tuple[np.ndarray, np.ndarray]:
    """For each pixel of a level, its up to 4 neighbours rendered before it (on the grid of
    twice the spacing, one spacing away in each axis), as (N,4,2) (v, u) and a (N,4) mask, in
    the order (-,-), (-,+), (+,-), (+,+) of the offsets (an offset of 0 repeats a neighbour,
    which the mask drops)."""
    found, valid = [], []
    for dv in (-1, 1):
        for du in (-1, 1):
            v, u = pixels[:, 0].copy(), pixels[:, 1].copy()
            odd_v, odd_u = v % (2 * spacing) != 0, u % (2 * spacing) != 0
            v = np.where(odd_v, v + dv * spacing, v)
            u = np.where(odd_u, u + du * spacing, u)
            ok = (v < height) & (u < width)
            # An even axis has one neighbour, not two: keep the (-) offset's copy only.
            ok &= (odd_v | (dv < 0)) & (odd_u | (du < 0))
            found.append(np.stack([np.minimum(v, height - 1), np.minimum(u, width - 1)], axis=1))
            valid.append(ok)
    return np.stack(found, axis=1), np.stack(valid, axis=1)


# Fitted sample counts are multiples of this, so a level runs a few counts, not dozens (the
# server's ``SAMPLE_QUANTUM``).
SAMPLE_QUANTUM = 4


def dilate(score: np.ndarray) -> np.ndarray:
    """The neighbours' weights (N,S) dilated by one sample (half a neighbour's score): a surface
    between two samples is seen by both."""
    shifted = np.pad(score, ((0, 0), (1, 1)))
    return np.maximum(score, np.float32(0.5) * np.maximum(shifted[:, :-2], shifted[:, 2:]))


def support(score: np.ndarray, threshold: float) -> np.ndarray:
    """How many samples of each ray the neighbours' (dilated) weights (N,S) count as matter (N)."""
    return (dilate(score) >= np.float32(threshold)).sum(axis=1)


def select_samples(score: np.ndarray, count: int, threshold: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ``count`` samples of each ray to run, from its neighbours' weights ``score`` (N,S).

    The score is dilated by one sample (half a neighbour's score): a surface between two samples
    is seen by both. The samples with the highest dilated scores are taken (ties: the nearer to
    the best sample, then the lower index). Every sample whose dilated score reaches
    ``threshold`` (the support: where a neighbour saw matter) and is not taken is stood for by
    the nearest taken one (ties: the lower), so each taken sample has a multiplicity >= 1.
    Returns sample indices (N,K) increasing, multiplicities (N,K) and, per uniform sample, the
    position of the taken sample that stands for it, or -1 (N,S)."""
    n, s = score.shape
    dilated = dilate(score)
    best = np.argmax(dilated, axis=1)
    distance = np.abs(np.arange(s)[None, :] - best[:, None])
    # lexsort: the last key is the primary one.
    order = np.lexsort((np.broadcast_to(np.arange(s), (n, s)), distance, -dilated), axis=1)
    index = np.sort(order[:, :count], axis=1)
    members = dilated >= threshold
    members[np.arange(n)[:, None], index] = True
    owner = nearest_taken(index, s)
    owner = np.where(members, owner, -1)
    multiplicity = np.zeros((n, count), np.float32)
    np.add.at(multiplicity, (np.nonzero(owner >= 0)[0], owner[owner >= 0]), 1.0)
    return index, multiplicity, owner


def spread_samples(score: np.ndarray, count: int, threshold: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What a pixel rendered again runs, from its neighbours' weights ``score`` (N,S): their
    support (the samples whose dilated score reaches ``threshold``; where those are more than half
    of ``count``, the heaviest half, ties: the lower index) and the rest spread evenly over the
    samples left (the i-th of the m left of r to take: left[i*m // r]). Every sample is stood for
    by the nearest taken one (ties: the lower): the pixel disagreed with its neighbours, so matter
    may lie where they saw none. ``count`` = S: every sample. Returned as :func:`select_samples`
    returns its selection."""
    dilated = dilate(score)
    n, s = score.shape
    count = min(count, s)
    index = np.zeros((n, count), np.int64)
    for r in range(n):
        kept = np.nonzero(dilated[r] >= np.float32(threshold))[0]
        if len(kept) > count // 2:
            kept = kept[np.lexsort((kept, -dilated[r, kept]))][: count // 2]
        left = np.setdiff1d(np.arange(s), kept)
        rest = count - len(kept)
        index[r] = np.sort(np.concatenate([kept, left[np.arange(rest) * len(left) // max(rest, 1)]]))
    owner = nearest_taken(index, s)
    multiplicity = np.zeros((n, count), np.float32)
    np.add.at(multiplicity, (np.repeat(np.arange(n), s), owner.ravel()), 1.0)
    return index, multiplicity, owner


def nearest_taken(index: np.ndarray, samples: int) -> np.ndarray:
    """For every uniform sample, the position in ``index`` (N,K, increasing) of the nearest taken
    sample, the lower on a tie: (N,S)."""
    n, k = index.shape
    grid = np.arange(samples)
    after = np.stack([np.searchsorted(row, grid) for row in index])  # first taken >= sample
    lower = np.clip(after - 1, 0, k - 1)
    upper = np.clip(after, 0, k - 1)
    rows = np.arange(n)[:, None]
    to_lower = np.abs(grid[None, :] - index[rows, lower])
    to_upper = np.abs(index[rows, upper] - grid[None, :])
    return np.where(to_lower <= to_upper, lower, upper)


def spread_weights(weights: np.ndarray, multiplicity: np.ndarray, owner: np.ndarray) -> np.ndarray:
    """A fine ray's weights over all S samples, for the levels after it: each taken sample's
    weight shared among the samples it stands for."""
    share = weights / multiplicity
    rows = np.arange(owner.shape[0])[:, None]
    return np.where(owner >= 0, share[rows, np.maximum(owner, 0)], np.float32(0.0)).astype(np.float32)


def disagreement(own: np.ndarray, near: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """How far each pixel's outputs lie outside its neighbours': ``own`` (N,4) and ``near``
    (N,4,4) composited colour and opacity; the largest distance of the colour outside the
    neighbours' range in a channel, or of the opacity below their lowest (N), float32."""
    low, high = _range(near[..., :3], valid)
    colour = np.maximum(np.maximum(low - own[:, :3], own[:, :3] - high).max(axis=1), np.float32(0.0))
    lowest = np.where(valid, near[..., 3], np.inf).min(axis=1)
    return np.maximum(colour, lowest - own[:, 3]).astype(np.float32)


def disagreeing(policy: GuidedPolicy, gap: np.ndarray) -> np.ndarray:
    """Which of a level's K-sample pixels (their :func:`disagreement` ``gap``, row by row) are
    rendered again: those beyond ``verify_tolerance``, the worst first (ties: the earlier), at
    most ``policy.most_reruns`` of them; a boolean mask."""
    again = np.zeros(len(gap), bool)
    if policy.verify_tolerance is None:
        return again
    beyond = np.nonzero(gap > np.float32(policy.verify_tolerance))[0]
    worst = beyond[np.lexsort((beyond, -gap[beyond]))][: policy.most_reruns(len(gap))]
    again[worst] = True
    return again


def samples_at(policy: GuidedPolicy, count: int, span: np.ndarray, support: np.ndarray) -> np.ndarray:
    """Samples per pixel of a level of ``count`` samples, from its neighbours' colour ``span`` and
    the samples their weights count as matter (``support``): more on an edge, where the policy
    says so; with ``min_samples``, the support rounded up to ``SAMPLE_QUANTUM``, at least
    ``min_samples``, at most that count (the server's ``GuidedPolicy::samples_at``)."""
    counts = np.full(span.shape, count)
    if policy.edge_span is not None:
        counts = np.where(span > np.float32(policy.edge_span), max(count, policy.edge_samples), counts)
    if policy.min_samples is None:
        return counts
    fitted = -(-np.minimum(support, counts) // SAMPLE_QUANTUM) * SAMPLE_QUANTUM
    return np.minimum(np.maximum(fitted, policy.min_samples), counts)


def nearest_guide(pixels: np.ndarray, grid_width: int, grid_height: int, step: int) -> np.ndarray:
    """The level-0 ray nearest each pixel (half-way: the later), as a row of the level-0 grid
    (row by row), float32 (the graph's input): its rectifier heads stand for the pixel's."""
    v = np.minimum((pixels[:, 0] + step // 2) // step, grid_height - 1)
    u = np.minimum((pixels[:, 1] + step // 2) // step, grid_width - 1)
    return (v * grid_width + u).astype(np.float32)


@dataclass
class GuidedView:
    """A view's raw outputs (before the background) and how it was sampled."""

    rgb: np.ndarray  # (H*W,3)
    depth: np.ndarray  # (H*W)
    opacity: np.ndarray  # (H*W)
    network_samples: int  # samples the network ran at, over all pixels
    interpolated: int  # pixels that took their neighbours' mean
    on_edge: int  # pixels that ran at more samples than their level's, on an edge
    rendered_again: int  # pixels rendered again at all S samples
    # Network samples by stage: "level 0", "grid N" (a level of spacing N), "rendered again".
    samples_by_stage: dict[str, int]


def render_guided(
    policy: GuidedPolicy,
    width: int,
    height: int,
    samples: int,
    origins: np.ndarray,
    directions: np.ndarray,
    background: np.ndarray,
    guide: GuideRun,
    fine: FineRun,
) -> GuidedView:
    """Every pixel of a ``width`` x ``height`` view (rays row by row) by the policy."""
    n = width * height
    rgb, depth, opacity = np.zeros((n, 3), np.float32), np.zeros(n, np.float32), np.zeros(n, np.float32)
    # The weights over all S samples of the pixels later levels read (every second row and column).
    guidance = np.zeros((n, samples), np.float32) if policy.step > 1 else None
    first = first_level_pixels(width, height, policy.step)
    rows = first[:, 0] * width + first[:, 1]
    out = guide(origins[rows], directions[rows])
    rgb[rows], depth[rows], opacity[rows] = out["rgb"], out["depth"], out["opacity"]
    if guidance is not None:
        guidance[rows] = out["weights"]
    grid_h, grid_w = (height - 1) // policy.step + 1, (width - 1) // policy.step + 1
    by_stage = {"level 0": len(rows) * samples}
    interpolated, on_edge, rendered_again = 0, 0, 0

    def run_fine(at: np.ndarray, selected: tuple, keeps_guidance: bool) -> int:
        """Pixels ``at`` (N,2) at their ``selected`` samples; returns the samples run."""
        if len(at) == 0:
            return 0
        index, multiplicity, owner = selected
        rows = at[:, 0] * width + at[:, 1]
        guide_rows = nearest_guide(at, grid_w, grid_h, policy.step)
        out = fine(origins[rows], directions[rows], index.astype(np.float32), multiplicity, guide_rows)
        rgb[rows], depth[rows], opacity[rows] = out["rgb"], out["depth"], out["opacity"]
        if keeps_guidance:
            guidance[rows] = spread_weights(out["weights"], multiplicity, owner)
        return len(rows) * index.shape[1]

    for spacing, count in policy.levels():
        pixels = level_pixels(width, height, spacing)
        near, valid = neighbours(pixels, width, height, spacing)
        near_rows = near[..., 0] * width + near[..., 1]
        colours = rgb[near_rows] + (1.0 - opacity[near_rows])[..., None] * background
        span = _span(colours, valid)
        smooth = np.zeros(len(pixels), bool)
        if spacing <= policy.smooth_max_step:
            smooth = (valid.sum(axis=1) >= 2) & (span <= np.float32(policy.smooth_tolerance))
        here = pixels[:, 0] * width + pixels[:, 1]
        keeps_guidance = spacing > 1
        if smooth.any():
            taken, of = near_rows[smooth], valid[smooth]
            rows = here[smooth]
            rgb[rows], depth[rows], opacity[rows] = (_masked_mean(a[taken], of) for a in (rgb, depth, opacity))
            if keeps_guidance:
                guidance[rows] = _masked_max(guidance[taken], of)
            interpolated += int(smooth.sum())
        run = ~smooth
        if not run.any():
            continue
        running = np.nonzero(run)[0]
        score = _masked_max(guidance[near_rows[running]], valid[running])
        counts = samples_at(policy, count, span[run], support(score, policy.support_threshold))
        counts = np.minimum(counts, samples)
        on_edge += int((counts > count).sum())
        for k in np.unique(counts):
            ray = counts == k
            selected = select_samples(score[ray], int(k), policy.support_threshold)
            by_stage[f"grid {spacing}"] = by_stage.get(f"grid {spacing}", 0) + run_fine(
                pixels[running[ray]], selected, keeps_guidance
            )
        rows = here[run]
        outputs = np.concatenate([rgb + (1.0 - opacity)[:, None] * background, opacity[:, None]], axis=1)
        again = disagreeing(policy, disagreement(outputs[rows], outputs[near_rows[run]], valid[run]))
        if again.any():
            spread = spread_samples(score[again], policy.rerun_samples(samples), policy.support_threshold)
            by_stage["rendered again"] = by_stage.get("rendered again", 0) + run_fine(
                pixels[running[again]], spread, keeps_guidance
            )
        rendered_again += int(again.sum())
    network_samples = sum(by_stage.values())
    return GuidedView(rgb, depth, opacity, network_samples, interpolated, on_edge, rendered_again, by_stage)


def _range(colours: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The lowest and highest of the valid neighbours' colours (N,4,C), per channel (N,C)."""
    high = np.where(valid[..., None], colours, -np.inf).max(axis=1)
    low = np.where(valid[..., None], colours, np.inf).min(axis=1)
    return low, high


def _span(colours: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """The largest spread of the valid neighbours' colours in a channel (N), float32."""
    low, high = _range(colours, valid)
    return (high - low).max(axis=1).astype(np.float32)


def _masked_mean(values: np.ndarray, valid: np.ndarray) -> np.ndarray:
    mask = valid.reshape(valid.shape + (1,) * (values.ndim - 2)).astype(np.float32)
    return ((values * mask).sum(axis=1) / mask.sum(axis=1)).astype(np.float32)


def _masked_max(values: np.ndarray, valid: np.ndarray) -> np.ndarray:
    mask = valid.reshape(valid.shape + (1,) * (values.ndim - 2))
    return np.where(mask, values, np.float32(0.0)).max(axis=1)


def guided_rendering(
    policy: GuidedPolicy, cfg, target: Camera, background, guide: GuideRun, fine: FineRun
) -> Rendering:
    """A target view by guided sampling, composited on ``background``: what both Python runtimes
    return."""
    if renderer_passes(cfg) == 2:
        raise ValueError("guided sampling needs depth_norm near_far (not a depth range from the whole image)")
    origins, directions = cams.target_rays(target)
    bg = np.asarray(background, dtype=np.float32)
    view = render_guided(policy, target.width, target.height, cfg.samples, origins, directions, bg, guide, fine)
    rgb = view.rgb + (1.0 - view.opacity[:, None]) * bg
    shape = (target.height, target.width)
    samples_per_ray = view.network_samples / (target.width * target.height)
    paths = {"interpolated": view.interpolated, "on_edge": view.on_edge, "rendered_again": view.rendered_again}
    return Rendering(
        rgb.reshape(*shape, 3),
        view.depth.reshape(shape),
        view.opacity.reshape(shape),
        samples_per_ray,
        paths,
        view.samples_by_stage,
    )
