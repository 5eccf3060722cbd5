"""Every recipe composes and computes what it did when recorded
(``tests/_recipe_record.py``, ``tests/data/recipe_configs.json`` and
``recipe_losses.pt``): a change of the kit's layout (where a recipe is written, how
options are read and checked) must leave every composed value, every loss output and
every gradient as it was. A change of a recipe itself records them again and says why in
its commit."""

from __future__ import annotations

import json

import pytest
import torch
from _composed_configs import compose_leaves, key
from _recipe_record import CONFIG_RECORD, RECORD, combos, config_combos, recipe_outputs
from _tolerance import assert_close_f32

CONFIGS = json.loads(CONFIG_RECORD.read_text())


def test_the_record_holds_every_combination():
    assert sorted(CONFIGS) == sorted(key(c) for c in config_combos())
    assert sorted(torch.load(RECORD, weights_only=True)) == sorted(f"{a} {e}" for a, e in combos())


@pytest.mark.parametrize("overrides", config_combos(), ids=key)
def test_each_combination_composes_its_recorded_config(overrides):
    assert compose_leaves(overrides) == CONFIGS[key(overrides)]


@pytest.mark.parametrize("algo, env", combos(), ids=[f"{a}-{e}" for a, e in combos()])
def test_each_recipes_loss_and_gradients_equal_the_record(algo, env):
    expected = torch.load(RECORD, weights_only=True)[f"{algo} {env}"]
    now = recipe_outputs(algo, env)
    assert sorted(now) == sorted(expected)
    for name, value in expected.items():
        # width-32 layers and batch means of 24 rows: roundings of ~32-term sums
        assert_close_f32(now[name], value, ops=32, msg=name)
