"""The plane sweep outside ONNX (runtime/plane_sweep.py, the server's pipeline::sweep in numpy)
against the cost volume's definition in PyTorch (model.cost_volume.build_cost_volume)."""

import numpy as np
import torch
import torch.nn.functional as F

from scnerf_export.config import small_config
from scnerf_export.model.cost_volume import build_cost_volume, slab_halo
from scnerf_export.model.layers import normalise_imagenet
from scnerf_export.rigs import random_model, synthetic_rig
from scnerf_export.runtime.plane_sweep import quarter_images, sweep
from scnerf_export.train.refine_bank import sweep_in_torch


def rig_and_features(seed=1):
    cfg = small_config("scnerf")
    rig = synthetic_rig(cfg, 96, 64, seed=seed)
    with torch.no_grad():
        features = random_model(cfg, seed).encode(rig["images"])
    return cfg, rig, features


def test_quarter_images_are_pytorchs_to_the_last_bit():
    _, rig, features = rig_and_features()
    want = F.interpolate(normalise_imagenet(rig["images"]), size=features.shape[2:], mode="bilinear").numpy()
    # PyTorch's kernel sums the four pixels in an order that depends on the size: one ulp apart.
    got = quarter_images(rig["images"].numpy())
    assert np.abs(got - want).max() <= 4 * np.spacing(np.abs(want).max())


def test_the_sweep_is_the_cost_volume_and_zero_beyond_the_volume():
    cfg, rig, features = rig_and_features()
    index, inside = slab_halo(cfg.depth_planes, 0, 6)  # a first slab: its front halo plane is outside
    planes = rig["depth_planes"][torch.from_numpy(index)]
    with torch.no_grad():
        want = build_cost_volume(features, rig["images"], rig["projections"], planes, cfg.pad).numpy()
    got = sweep(features.numpy(), rig["images"].numpy(), rig["projections"].numpy(), planes.numpy(), inside, cfg.pad)
    assert got.shape == want.shape == (1, 9 + cfg.feature_channels, 8, 24 + 2 * cfg.pad, 16 + 2 * cfg.pad)
    assert not got[:, :, 0].any()
    # The homographies' float32 rounding differs from PyTorch's matrix products: ~1e-5 px.
    assert np.abs(got[:, :, 1:] - want[:, :, 1:]).max() < 1e-4
    assert np.abs(want[:, 9:]).max() > 1.0, "a cost volume worth comparing"


def test_the_sweep_refine_banks_with_is_the_servers():
    cfg, rig, features = rig_and_features(seed=2)
    index, inside = slab_halo(cfg.depth_planes, cfg.depth_planes - 5, cfg.depth_planes)  # a last slab
    args = (features.numpy(), rig["images"].numpy(), rig["projections"].numpy(), rig["depth_planes"].numpy()[index])
    want, got = sweep(*args, inside, cfg.pad), sweep_in_torch(*args, inside, cfg.pad)
    assert not got[:, :, -1].any() and inside[-1] == 0
    assert np.abs(got - want).max() < 1e-4
