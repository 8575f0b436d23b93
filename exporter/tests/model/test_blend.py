"""blend-heads: the line between the initial and the trained heads, and the per-view choice on it."""

import pytest
import torch

from scnerf_export.config import small_config
from scnerf_export.model.checkpoint import save_checkpoint
from scnerf_export.rigs import random_model
from scnerf_export.train.blend import blend_heads, blended, choose_alpha, guards


def test_blended_ends_are_the_two_checkpoints_and_the_middle_is_halfway():
    theta_0 = random_model(small_config("scnerf"), seed=0).state_dict()
    theta_1 = random_model(small_config("scnerf"), seed=1).state_dict()
    for alpha, expected in ((0.0, theta_0), (1.0, theta_1)):
        out = blended(theta_0, theta_1, alpha)
        for k, v in expected.items():
            assert torch.allclose(out[k].float(), v.float(), atol=1e-6), k
    middle = blended(theta_0, theta_1, 0.5)
    k = next(k for k, v in theta_0.items() if v.is_floating_point() and not torch.equal(v, theta_1[k]))
    assert torch.allclose(middle[k], (theta_0[k] + theta_1[k]) / 2, atol=1e-6)


def table(*rows):
    """alpha -> scores for two lego views with nearest sources (r_28 guarded) and one with fixed."""
    keys = ("lego/r_28/nearest/psnr", "lego/r_63/nearest/psnr", "lego/r_63/fixed/psnr")
    return {alpha: dict(zip(keys, values)) for alpha, *values in rows}


def test_alpha_is_the_best_mean_gain_that_keeps_every_guard():
    rows = table(
        (0.0, 24.0, 14.0, 10.0),
        (0.5, 24.1, 14.5, 9.5),  # a fixed-sources view may lose
        (1.0, 23.9, 16.0, 11.0),  # the largest mean gain, but the guarded view r_28 loses
    )
    assert choose_alpha(rows) == 0.5


def test_the_scene_mean_with_the_nearest_sources_is_guarded():
    rows = table((0.0, 24.0, 14.0, 10.0), (1.0, 24.0, 13.9, 12.0))
    assert guards(rows[1.0])["lego/mean/nearest/psnr"] < guards(rows[0.0])["lego/mean/nearest/psnr"]
    assert choose_alpha(rows) == 0.0


def test_alpha_is_zero_when_every_blend_loses_a_guard():
    assert choose_alpha(table((0.0, 24.0, 14.0, 10.0), (0.5, 23.99, 15.0, 11.0), (1.0, 23.0, 18.0, 12.0))) == 0.0


def test_a_trained_checkpoint_with_another_backbone_is_refused(tmp_path):
    init = random_model(small_config("scnerf"), seed=0)
    other = random_model(small_config("scnerf"), seed=1)
    save_checkpoint(tmp_path / "init.pt", init, {})
    save_checkpoint(tmp_path / "other.pt", other, {})
    with pytest.raises(ValueError, match="only the heads"):
        blend_heads(tmp_path / "init.pt", tmp_path / "other.pt", tmp_path / "out.pt", tmp_path, tmp_path / "cache")
