"""Image and depth metrics for evaluation (numpy only; LPIPS optional).

- ``psnr``: 10 log10(1 / MSE) for images in [0, 1]; with a mask, the MSE is the mean over the
  masked pixels and the 3 channels.
- ``ssim``: the standard gaussian-window SSIM (11x11, sigma 1.5, K1 0.01, K2 0.03, data range 1),
  computed on the "valid" region (no padding) and averaged over channels. This is the
  JAX-NeRF / MVSNeRF ``rgb_ssim`` and equals skimage's ``structural_similarity(channel_axis=-1,
  data_range=1, gaussian_weights=True, sigma=1.5, use_sample_covariance=False)`` (skimage
  filters with a truncated 11-tap gaussian and crops the 5-pixel border, i.e. the valid region).
- ``dtu_masked_metrics``: MVSNeRF's DTU protocol: PSNR on object pixels only, SSIM (and LPIPS) on
  images whose background (mask False) is set to 0 in both prediction and ground truth.
- ``depth_metrics``: mean absolute error over pixels with ground truth (gt > 0), and the fraction
  of those within 0.01 and 0.05 scene units (SC-NeRF Table 3 / MVSNeRF, DTU world scaled 1/200).
- ``lpips``: the `lpips` package (v0.1) if it and torchvision's ImageNet-pretrained backbone
  weights are available locally; otherwise :class:`LpipsUnavailable` says why.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

__all__ = [
    "psnr",
    "mse",
    "ssim",
    "dtu_masked_metrics",
    "depth_metrics",
    "lpips",
    "lpips_available",
    "LpipsUnavailable",
    "mean_metrics",
]

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_K1 = 0.01
SSIM_K2 = 0.03


def _as_image(x, name: str) -> np.ndarray:
    a = np.asarray(x)
    if a.dtype == np.uint8:
        a = a.astype(np.float64) / 255.0
    else:
        a = a.astype(np.float64)
    if a.ndim == 2:
        a = a[..., None]
    if a.ndim != 3:
        raise ValueError(f"{name} must be (H,W) or (H,W,C), got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} contains non-finite values")
    return a


def _pair(pred, gt) -> tuple[np.ndarray, np.ndarray]:
    p, g = _as_image(pred, "pred"), _as_image(gt, "gt")
    if p.shape != g.shape:
        raise ValueError(f"pred and gt shapes differ: {p.shape} vs {g.shape}")
    return p, g


def _as_mask(mask, shape, name="mask") -> np.ndarray:
    m = np.asarray(mask)
    if m.ndim == 3 and m.shape[-1] == 1:
        m = m[..., 0]
    if m.shape != tuple(shape[:2]):
        raise ValueError(f"{name} shape {m.shape} does not match the image's {tuple(shape[:2])}")
    return m.astype(bool)


def mse(pred, gt, mask=None) -> float:
    """Mean squared error over all pixels and channels, or over the masked pixels (all channels)."""
    p, g = _pair(pred, gt)
    err = (p - g) ** 2
    if mask is None:
        return float(err.mean())
    m = _as_mask(mask, p.shape)
    if not m.any():
        raise ValueError("mask selects no pixel")
    return float(err[m].mean())


def psnr(pred, gt, mask=None) -> float:
    """PSNR in dB for images in [0, 1] (uint8 inputs are divided by 255). Identical -> inf."""
    e = mse(pred, gt, mask)
    if e == 0.0:
        return math.inf
    return float(-10.0 * math.log10(e))


def _gaussian_window(size: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA) -> np.ndarray:
    x = np.arange(size, dtype=np.float64) - (size - 1) / 2.0
    w = np.exp(-0.5 * (x / sigma) ** 2)
    return w / w.sum()


def _filter_valid(x: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Separable 'valid' correlation of (H,W,C) with the 1-D window w along H then W."""
    k = len(w)
    h, wd = x.shape[0] - k + 1, x.shape[1] - k + 1
    y = sum(w[i] * x[i : i + h] for i in range(k))
    return sum(w[i] * y[:, i : i + wd] for i in range(k))


def ssim(pred, gt, return_map: bool = False):
    """Gaussian-window SSIM (11x11, sigma 1.5, K1 0.01, K2 0.03, data range 1), channel-averaged,
    over the valid region (images must be at least 11x11)."""
    p, g = _pair(pred, gt)
    if p.shape[0] < SSIM_WINDOW or p.shape[1] < SSIM_WINDOW:
        raise ValueError(f"SSIM needs images of at least {SSIM_WINDOW}x{SSIM_WINDOW}, got {p.shape[1]}x{p.shape[0]}")
    w = _gaussian_window()
    mu_p, mu_g = _filter_valid(p, w), _filter_valid(g, w)
    s_pp = _filter_valid(p * p, w) - mu_p**2
    s_gg = _filter_valid(g * g, w) - mu_g**2
    s_pg = _filter_valid(p * g, w) - mu_p * mu_g
    # numerical guards of JAX-NeRF / MVSNeRF's rgb_ssim (no-ops up to rounding)
    s_pp = np.maximum(0.0, s_pp)
    s_gg = np.maximum(0.0, s_gg)
    s_pg = np.sign(s_pg) * np.minimum(np.sqrt(s_pp * s_gg), np.abs(s_pg))
    c1, c2 = SSIM_K1**2, SSIM_K2**2
    smap = ((2 * mu_p * mu_g + c1) * (2 * s_pg + c2)) / ((mu_p**2 + mu_g**2 + c1) * (s_pp + s_gg + c2))
    return smap if return_map else float(smap.mean())


def dtu_masked_metrics(pred, gt, mask, with_lpips: bool = False, lpips_net: str = "vgg") -> dict:
    """MVSNeRF's DTU protocol: {'psnr': PSNR over mask pixels, 'ssim': SSIM of the images with
    the background (mask False) set to 0 in both}; with_lpips adds 'lpips' on those same images
    (raises LpipsUnavailable when LPIPS cannot run)."""
    p, g = _pair(pred, gt)
    m = _as_mask(mask, p.shape)
    out = {"psnr": psnr(p, g, m)}
    p0, g0 = p * m[..., None], g * m[..., None]
    out["ssim"] = ssim(p0, g0)
    if with_lpips:
        out["lpips"] = lpips(p0, g0, net=lpips_net)
    return out


def depth_metrics(pred, gt, valid=None, thresholds=(0.01, 0.05)) -> dict:
    """Depth errors on the pixels with ground truth (gt > 0 and finite, and ``valid`` if given):
    {'abs_err': mean |pred - gt|, 'acc_0.01': fraction with |pred - gt| < 0.01, 'acc_0.05': ...,
    'count': number of pixels used}. Units are the scene's (DTU: mm / 200). A non-finite
    prediction counts as an infinite error. No valid pixel ->
    abs_err and the accuracies are NaN."""
    p = np.asarray(pred, dtype=np.float64)
    g = np.asarray(gt, dtype=np.float64)
    if p.shape != g.shape:
        raise ValueError(f"pred and gt depth shapes differ: {p.shape} vs {g.shape}")
    m = np.isfinite(g) & (g > 0)
    if valid is not None:
        v = np.asarray(valid).astype(bool)
        if v.shape != g.shape:
            raise ValueError(f"valid mask shape {v.shape} does not match the depth's {g.shape}")
        m &= v
    n = int(m.sum())
    out = {"count": n}
    if n == 0:
        out["abs_err"] = math.nan
        for t in thresholds:
            out[f"acc_{t:g}"] = math.nan
        return out
    err = np.abs(p[m] - g[m])
    err[~np.isfinite(err)] = np.inf  # a non-finite prediction is simply wrong
    out["abs_err"] = float(err.mean())
    for t in thresholds:
        out[f"acc_{t:g}"] = float((err < t).mean())
    return out


def mean_metrics(rows: list[dict]) -> dict:
    """Per-key mean over a list of metric dicts (keys missing from a row are skipped; inf PSNRs
    make the mean inf, as they should)."""
    keys = []
    for r in rows:
        for k in r:
            if k not in keys:
                keys.append(k)
    out = {}
    for k in keys:
        vals = [r[k] for r in rows if k in r and isinstance(r[k], (int, float))]
        if vals:
            out[k] = float(np.mean(vals))
    return out


# ----------------------------------------------------------------------------- LPIPS


class LpipsUnavailable(RuntimeError):
    """LPIPS cannot be computed on this machine; the message says why and how to enable it."""


# torchvision's ImageNet backbones that lpips v0.1 loads through torchvision (pretrained=True)
_BACKBONE_FILES = {
    "alex": "alexnet-owt-7be5be79.pth",
    "vgg": "vgg16-397923af.pth",
    "squeeze": "squeezenet1_1-b8a52dc0.pth",
}
_LPIPS_MODELS: dict = {}


def lpips_available(net: str = "vgg") -> tuple[bool, str]:
    """(True, '') when lpips(net=...) can run offline, else (False, the reason)."""
    if net not in _BACKBONE_FILES:
        return False, f"unknown LPIPS network {net!r} (alex, vgg, squeeze)"
    try:
        import lpips as _lp  # noqa: F401
        import torch
        import torchvision  # noqa: F401
    except ImportError as e:
        return False, (
            f"the 'lpips' package (and torchvision) is not installed ({e}); "
            "`pip install lpips torchvision` provides the code and LPIPS's own linear layers"
        )
    ckpt = Path(torch.hub.get_dir()) / "checkpoints" / _BACKBONE_FILES[net]
    if not ckpt.is_file():
        return False, (
            f"LPIPS needs torchvision's ImageNet-pretrained {net} backbone weights "
            f"({_BACKBONE_FILES[net]}), which torchvision downloads from download.pytorch.org "
            f"at first use; no package on a reachable registry ships them and that host is "
            f"not reachable here. Put the file at {ckpt} (or set TORCH_HOME) to enable LPIPS."
        )
    return True, ""


def lpips(pred, gt, net: str = "vgg") -> float:
    """LPIPS v0.1 distance between two (H,W,3) images in [0,1] (MVSNeRF: normalize=True, VGG).
    Raises LpipsUnavailable when the package or the backbone weights are not available offline."""
    ok, why = lpips_available(net)
    if not ok:
        raise LpipsUnavailable(why)
    import lpips as _lp
    import torch

    p, g = _pair(pred, gt)
    if p.shape[-1] != 3:
        raise ValueError(f"LPIPS needs 3-channel images, got {p.shape[-1]}")
    if net not in _LPIPS_MODELS:
        # the backbone file is present: torchvision loads it from the hub cache without network
        _LPIPS_MODELS[net] = _lp.LPIPS(net=net, version="0.1", verbose=False).eval()
    model = _LPIPS_MODELS[net]
    tp = torch.from_numpy(p.astype(np.float32)).permute(2, 0, 1)[None]
    tg = torch.from_numpy(g.astype(np.float32)).permute(2, 0, 1)[None]
    with torch.no_grad():
        return float(model(tg, tp, normalize=True).item())
