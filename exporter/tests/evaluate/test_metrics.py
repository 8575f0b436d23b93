"""Image and depth metrics."""

from __future__ import annotations

import math

import numpy as np
import pytest

from scnerf_export.evaluate import metrics as M


def rand_img(seed=0, shape=(48, 64, 3)):
    return np.random.default_rng(seed).random(shape)


def smooth_pair():
    y, x = np.mgrid[0:40, 0:48]
    a = np.stack([0.5 + 0.4 * np.sin(x / 3.0 + c) * np.cos(y / 5.0) for c in range(3)], -1)
    b = np.stack([0.5 + 0.35 * np.sin(x / 3.3 + c) * np.cos(y / 4.5 + 0.2) for c in range(3)], -1)
    return a, b


# ----------------------------------------------------------------------------- PSNR


def test_psnr_identical_is_inf():
    a = rand_img()
    assert M.psnr(a, a) == math.inf
    assert M.psnr(a, a, mask=np.ones(a.shape[:2], bool)) == math.inf


def test_psnr_known_mse():
    a = np.full((10, 12, 3), 0.5)
    b = a + 0.1  # MSE 0.01 -> 20 dB
    assert M.psnr(b, a) == pytest.approx(20.0, abs=1e-9)
    assert M.mse(b, a) == pytest.approx(0.01)
    c = a.copy()
    c[..., 0] += 0.1  # MSE 0.01/3
    assert M.psnr(c, a) == pytest.approx(10 * math.log10(300), abs=1e-9)


def test_psnr_uint8_inputs():
    a = np.zeros((4, 4, 3), np.uint8)
    b = np.full((4, 4, 3), 255, np.uint8)
    assert M.psnr(a, b) == pytest.approx(0.0)


def test_masked_psnr_ignores_unmasked_pixels():
    gt = rand_img(1)
    pred = gt.copy()
    mask = np.zeros(gt.shape[:2], bool)
    mask[10:30, 20:40] = True
    pred[~mask] = 1.0 - gt[~mask]  # garbage outside the mask
    pred[mask] += 0.05  # MSE 0.0025 inside -> 26.0206 dB
    assert M.psnr(pred, gt, mask) == pytest.approx(-10 * math.log10(0.0025), abs=1e-9)
    assert M.psnr(pred, gt) < M.psnr(pred, gt, mask) - 5


def test_psnr_errors():
    a = rand_img()
    with pytest.raises(ValueError, match="shapes differ"):
        M.psnr(a, a[:-1])
    with pytest.raises(ValueError, match="no pixel"):
        M.psnr(a, a, mask=np.zeros(a.shape[:2], bool))
    with pytest.raises(ValueError, match="mask shape"):
        M.psnr(a, a, mask=np.ones((3, 3), bool))
    bad = a.copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        M.psnr(bad, a)


# ----------------------------------------------------------------------------- SSIM


def test_ssim_identical_is_one():
    a = rand_img()
    assert M.ssim(a, a) == pytest.approx(1.0, abs=1e-12)
    assert M.ssim(np.zeros((16, 16, 3)), np.zeros((16, 16, 3))) == pytest.approx(1.0)


def test_ssim_decreases_with_noise():
    a, _ = smooth_pair()
    rng = np.random.default_rng(0)
    vals = [M.ssim(np.clip(a + rng.normal(0, s, a.shape), 0, 1), a) for s in (0.0, 0.02, 0.05, 0.1, 0.2)]
    assert all(x > y for x, y in zip(vals, vals[1:])), vals
    assert vals[0] == pytest.approx(1.0) and vals[-1] < 0.7


def test_ssim_is_symmetric_and_channel_averaged():
    a, b = smooth_pair()
    assert M.ssim(a, b) == pytest.approx(M.ssim(b, a), abs=1e-12)
    per_channel = [M.ssim(a[..., c], b[..., c]) for c in range(3)]
    assert M.ssim(a, b) == pytest.approx(np.mean(per_channel), abs=1e-12)


def test_ssim_matches_recorded_skimage_value():
    """skimage 0.26 structural_similarity(channel_axis=-1, data_range=1, gaussian_weights=True,
    sigma=1.5, use_sample_covariance=False) on this analytic pair gave 0.5154247317121344."""
    a, b = smooth_pair()
    assert M.ssim(a, b) == pytest.approx(0.5154247317121344, abs=1e-9)


def test_ssim_matches_skimage():
    skm = pytest.importorskip("skimage.metrics", reason="scikit-image not installed")
    rng = np.random.default_rng(5)
    for shape in ((40, 48, 3), (33, 57, 3), (64, 64, 1)):
        a = rng.random(shape)
        b = np.clip(a + rng.normal(0, 0.1, shape), 0, 1)
        ref = skm.structural_similarity(
            a, b, channel_axis=-1, data_range=1.0, gaussian_weights=True, sigma=1.5, use_sample_covariance=False
        )
        assert M.ssim(a, b) == pytest.approx(ref, abs=1e-9)


def test_ssim_too_small():
    with pytest.raises(ValueError, match="at least 11x11"):
        M.ssim(np.zeros((8, 8, 3)), np.zeros((8, 8, 3)))


# ----------------------------------------------------------------------------- DTU protocol


def test_dtu_masked_metrics():
    gt = rand_img(2, (64, 80, 3))
    mask = np.zeros(gt.shape[:2], bool)
    mask[16:48, 20:60] = True
    pred = gt.copy()
    pred[mask] = np.clip(pred[mask] + 0.03, 0, 1)
    pred[~mask] = np.random.default_rng(3).random(pred[~mask].shape)  # background differs
    out = M.dtu_masked_metrics(pred, gt, mask)
    assert set(out) == {"psnr", "ssim"}
    assert out["psnr"] == pytest.approx(M.psnr(pred, gt, mask))
    # SSIM is on images with the background set to 0: background content does not matter
    assert out["ssim"] == pytest.approx(M.ssim(pred * mask[..., None], gt * mask[..., None]))
    pred2 = pred.copy()
    pred2[~mask] = 0.5
    assert M.dtu_masked_metrics(pred2, gt, mask) == pytest.approx(out)
    assert out["ssim"] > M.ssim(pred, gt)


# ----------------------------------------------------------------------------- depth


def test_depth_metrics():
    gt = np.array([[2.0, 3.0, 0.0], [4.0, 2.5, 3.5]])
    pred = np.array([[2.005, 3.02, 9.0], [4.1, 2.5, np.nan]])
    out = M.depth_metrics(pred, gt)
    # valid: 5 pixels (gt 0 ignored); errors 0.005, 0.02, 0.1, 0, inf (non-finite prediction)
    assert out["count"] == 5
    assert out["abs_err"] == math.inf
    assert out["acc_0.01"] == pytest.approx(2 / 5)
    assert out["acc_0.05"] == pytest.approx(3 / 5)
    valid = np.ones_like(gt, bool)
    valid[1, 2] = False
    out = M.depth_metrics(pred, gt, valid=valid)
    assert out["count"] == 4
    assert out["abs_err"] == pytest.approx((0.005 + 0.02 + 0.1 + 0.0) / 4)
    assert out["acc_0.01"] == pytest.approx(0.5) and out["acc_0.05"] == pytest.approx(0.75)


def test_depth_metrics_no_ground_truth():
    out = M.depth_metrics(np.ones((3, 3)), np.zeros((3, 3)))
    assert out["count"] == 0 and math.isnan(out["abs_err"]) and math.isnan(out["acc_0.01"])
    with pytest.raises(ValueError, match="shapes differ"):
        M.depth_metrics(np.ones((3, 3)), np.ones((3, 4)))


def test_mean_metrics():
    rows = [{"psnr": 20.0, "ssim": 0.5}, {"psnr": 30.0, "ssim": 0.7, "lpips": 0.1}]
    assert M.mean_metrics(rows) == pytest.approx({"psnr": 25.0, "ssim": 0.6, "lpips": 0.1})


# ----------------------------------------------------------------------------- LPIPS


def test_lpips_available_or_explains_why():
    ok, why = M.lpips_available("vgg")
    a = rand_img(0, (32, 32, 3))
    if ok:
        assert M.lpips(a, a) == pytest.approx(0.0, abs=1e-6)
    else:
        assert why
        with pytest.raises(M.LpipsUnavailable) as e:
            M.lpips(a, a)
        assert str(e.value) == why
        with pytest.raises(M.LpipsUnavailable):
            M.dtu_masked_metrics(a, a, np.ones((32, 32), bool), with_lpips=True)
    assert M.lpips_available("resnet")[0] is False
