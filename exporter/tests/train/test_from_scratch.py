"""Training from scratch (scnerf_export.train.from_scratch) on a tiny procedural scene: optimiser
steps lower the loss, and a run writes a checkpoint that holds the trained model exactly (it
reloads with the same parameters, and a run resumed from it matches one never interrupted)."""

import json
import math

import numpy as np
import torch

from scnerf_export.config import ModelConfig
from scnerf_export.data.procedural import ProceduralDataset
from scnerf_export.model.checkpoint import load_checkpoint
from scnerf_export.model.network import SCNeRF
from scnerf_export.train.from_scratch import Preset, train, training_step

# As small as the network's shape rules allow: planes a multiple of 8, images of 32.
TINY = ModelConfig(variant="scnerf", depth_planes=8, samples=8, pad=8, width=16, colour_hidden=8, heads=2, head_dim=4)
SIZE, VIEWS = 32, 6


def tiny_preset() -> Preset:
    return Preset(
        "tiny",
        TINY,
        width=SIZE,
        height=SIZE,
        rays=128,
        steps=2,
        train_scenes=1,
        gaps=("small",),
        checkpoint_every=1,
        validate_every=2,
        views=VIEWS,
        validation_scenes=1,
    )


def test_steps_on_one_batch_lower_the_loss():
    # A forward-facing scene: its target is textured wall to wall. (On the first object scene, with
    # its black background, this tiny network's initial densities are all zero: no gradient.)
    scenes = ProceduralDataset("train", n_scenes=1, layouts=("forward",), n_views=VIEWS, width=SIZE, height=SIZE)
    example = scenes.example(0, 0, "small")
    torch.manual_seed(0)
    model = SCNeRF(TINY).train()
    optimiser = torch.optim.Adam(model.parameters(), lr=5e-4)
    # The same generator state each step: the same rays, so the steps descend one loss.
    losses = [training_step(model, optimiser, example, 256, np.random.default_rng(0), "cpu") for _ in range(4)]
    assert all(math.isfinite(loss) for loss in losses)
    assert losses[-1] < losses[0]


def test_a_run_writes_a_checkpoint_of_the_trained_model(tmp_path):
    cache = tmp_path / "scenes"
    last = train(tiny_preset(), tmp_path / "run", steps=2, seed=0, cache_dir=cache)
    records = [json.loads(line) for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in records] == [1, 2]
    assert all(math.isfinite(r["loss"]) for r in records) and records[0]["loss"] != records[1]["loss"]
    assert all(math.isfinite(psnr) for psnr in records[-1]["val_psnr"].values())

    saved = torch.load(last, weights_only=False)
    model, provenance = load_checkpoint(last)
    assert model.cfg == TINY and saved["step"] == 2 and provenance["training"]["steps"] == 2
    state = model.state_dict()
    assert state.keys() == saved["state_dict"].keys()
    assert all(torch.equal(state[k], saved["state_dict"][k]) for k in state)
    torch.manual_seed(0)  # the run's seed: its initialisation
    initial = SCNeRF(TINY).state_dict()
    assert any(not torch.equal(initial[k], state[k]) for k in state)

    # One step, then resumed from its checkpoint for the second: the model of the run above.
    train(tiny_preset(), tmp_path / "resumed", steps=1, seed=0, cache_dir=cache)
    resumed = train(tiny_preset(), tmp_path / "resumed", resume=True, steps=2, seed=0, cache_dir=cache)
    again = load_checkpoint(resumed)[0].state_dict()
    assert all(torch.equal(again[k], state[k]) for k in state)
