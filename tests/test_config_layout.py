"""What ``conf/`` composes equals what it composed when it was recorded.

``tests/data/composed_configs.json`` holds every algorithm × env, row × env and
experiment (with each row it sweeps) as it composed before the recipes moved into one
file per algorithm (``tests/_composed_configs.py``); each combination composes the
same job config today, key by key.
"""

from __future__ import annotations

import json

import pytest
from _composed_configs import FIXTURE, combinations, compose_leaves, key

RECORDED = json.loads(FIXTURE.read_text())


def test_the_fixture_records_every_combination():
    assert sorted(RECORDED) == sorted(key(c) for c in combinations())


@pytest.mark.parametrize("overrides", combinations(), ids=key)
def test_each_combination_composes_what_was_recorded(overrides):
    then, now = RECORDED[key(overrides)], compose_leaves(overrides)
    assert sorted(now) == sorted(then)
    assert {k: v for k, v in now.items() if v != then[k]} == {}
