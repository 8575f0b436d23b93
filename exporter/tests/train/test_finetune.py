"""Fine-tuning the heads (scnerf_export.train.finetune) on rays of a tiny procedural scene: steps
on one batch lower the loss, and a two-step run moves only the heads and writes the chosen step's
heads to best.pt, which reloads with the same parameters."""

import copy
import json
import math

import pytest
import torch

from scnerf_export.config import ModelConfig
from scnerf_export.model.checkpoint import load_checkpoint
from scnerf_export.rigs import random_model
from scnerf_export.train.finetune import (
    HEADS,
    Recipe,
    head_parameter_groups,
    heads_step,
    train_heads,
    training_bank,
)

TINY = ModelConfig(variant="scnerf", depth_planes=8, samples=8, pad=8, width=16, colour_hidden=8, heads=2, head_dim=4)


@pytest.fixture(scope="module")
def initial(tmp_path_factory):
    """Random weights with mid-range opacity, and the heads' inputs for rays of two views of one
    32x32 procedural scene."""
    model = random_model(TINY, seed=3)
    cache = tmp_path_factory.mktemp("finetune")
    bank = training_bank(model, cache, 1, 2, 128, seed=0, width=32, height=32, views=6).storable()
    return model, bank


def is_head(key: str) -> bool:
    return key.split(".")[:2] in [["renderer", head] for head in HEADS]


def test_steps_on_one_batch_lower_the_loss(initial):
    model, bank = copy.deepcopy(initial[0]), initial[1]
    optimiser = torch.optim.Adam(head_parameter_groups(model, Recipe()))
    every_ray = torch.arange(len(bank))
    losses = [heads_step(model, optimiser, bank, every_ray) for _ in range(4)]
    assert all(math.isfinite(loss) for loss in losses)
    assert losses[-1] < losses[0]


def test_a_two_step_run_trains_the_heads_and_writes_the_chosen_step(initial, tmp_path):
    model, bank = copy.deepcopy(initial[0]), initial[1]
    before = {k: v.clone() for k, v in model.state_dict().items()}
    about = {"data": "one tiny procedural scene", "ray_bank_seconds": 0.0, "validation_scenes": ["the same rays"]}
    # Validated on the rays it trains on, at step 0 and step 2: step 2 scores better, and is chosen.
    recipe = Recipe(steps=2, rays=len(bank), validate_every=2)
    best = train_heads(model, bank, {"train": bank}, recipe, tmp_path, about, derived_from=None)

    records = [json.loads(line) for line in (tmp_path / "log.jsonl").read_text().splitlines()]
    losses = [r["loss"] for r in records if "loss" in r]
    assert len(losses) == 2 and all(math.isfinite(loss) for loss in losses) and losses[0] != losses[1]
    validated = [r["step"] for r in records if "validation" in r]
    assert validated == [0, 2]

    after = model.state_dict()
    moved = {k for k in after if not torch.equal(after[k], before[k])}
    assert moved and all(is_head(k) for k in moved)
    reloaded, provenance = load_checkpoint(best)
    assert provenance["training"]["steps"] == 2
    state = reloaded.state_dict()
    assert state.keys() == after.keys() and all(torch.equal(state[k], after[k]) for k in after)
