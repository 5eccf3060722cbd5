"""Values that used to pass silently and give NaN or inf losses, an option the chosen reading
never reads, and recipe state shared between callers: each is refused in one line (by the
loss and by the config, through the one definition of its rule) or made safe."""

from __future__ import annotations

import copy

import pytest
import torch
from _loss_helpers import plain_batch
from _training_helpers import compose_config
from torchrl.data import Bounded

from wcsac_rl import WCSACLoss
from wcsac_rl.modules import make_actor, make_qvalue, make_safety_critic
from wcsac_rl.objectives import PAPER_OPTIONS, loss_parts, recipe_options
from wcsac_rl.options import NUMBER_CEILING
from wcsac_rl.training.config import ConfigError, validate_config

SPEC = Bounded(-1.0, 1.0, shape=(2,))


def _loss(members: int = 1, **keywords) -> WCSACLoss:
    torch.manual_seed(0)
    safety = [make_safety_critic(4, 2, width=8) for _ in range(members)]
    return WCSACLoss(
        make_actor(4, SPEC, width=8), make_qvalue(4, 2, width=8),
        safety if members > 1 else safety[0], risk_level=0.1, cost_limit=15.0,
        action_spec=SPEC, **keywords,
    )  # fmt: skip


BAD_NUMBERS = [
    ("alpha_init", float("nan"), "alpha_init must be in (0, 1e+06] (a number), got nan"),
    ("alpha_init", float("inf"), "alpha_init must be in (0, 1e+06] (a number), got inf"),
    ("alpha_init", -1.0, "alpha_init must be in (0, 1e+06] (a number), got -1.0"),
    ("kappa_init", 1e300, "kappa_init must be in [0, 1e+06] (a number), got 1e+300"),
    ("kappa_init", float("inf"), "kappa_init must be in [0, 1e+06] (a number), got inf"),
    ("damp_scale", float("inf"), "damp_scale must be in [0, 1e+06] (a number), got inf"),
    ("prior_scale", 1e30, "prior_scale must be in [0, 1e+06] (a number), got 1e+30"),
]


@pytest.mark.parametrize(("name", "value", "message"), BAD_NUMBERS)
def test_the_loss_refuses_a_value_that_would_make_its_losses_nan_or_inf(name, value, message):
    recipe = {**PAPER_OPTIONS, "num_safety_nets": 2, name: value}
    with pytest.raises(ValueError) as err:
        _loss(members=2, **loss_parts(recipe))
    assert str(err.value) == message


@pytest.mark.parametrize(("name", "value", "message"), BAD_NUMBERS)
def test_the_config_refuses_the_same_value_with_the_same_words(name, value, message):
    cfg = compose_config("algo=cal", "env=tiny")  # (an ensemble: prior_scale is read)
    cfg.algo[name] = value
    with pytest.raises(ConfigError) as err:
        validate_config(cfg)
    assert str(err.value) == f"algo.{message}"


def test_the_largest_allowed_value_still_gives_finite_losses():
    """The ceiling is not itself a value that overflows the float32 losses."""
    loss = _loss(**loss_parts({**PAPER_OPTIONS, "kappa_init": NUMBER_CEILING}))
    out = loss(plain_batch(16, seed=1))
    assert all(torch.isfinite(v) for k, v in out.items() if k.startswith("loss_"))


def test_k_ucb_is_refused_where_the_reading_never_reads_it():
    with pytest.raises(ValueError) as err:
        _loss(members=2, **loss_parts({**PAPER_OPTIONS, "num_safety_nets": 2, "k_ucb": 3.0}))
    assert str(err.value) == (
        "k_ucb=3 weighs the members' spread in the UCB reading, which this one does not "
        "read: it needs ensemble_reading=ucb, got max"
    )
    cfg = compose_config("algo=wcsac", "env=tiny", "algo.num_safety_nets=2", "algo.k_ucb=3.0")
    with pytest.raises(ConfigError, match=r"^algo\.k_ucb=3 weighs .* got max$"):
        validate_config(cfg)
    # the UCB reading takes it
    ucb = {**PAPER_OPTIONS, "num_safety_nets": 2, "ensemble_reading": "ucb", "k_ucb": 3.0}
    assert _loss(members=2, **loss_parts(ucb)).safety_head.k_ucb == 3.0


def test_a_recipe_is_read_only_all_the_way_down():
    recipe = recipe_options("wcsac", "dynamic")
    with pytest.raises(TypeError):
        recipe["pid"]["ki"] = 5.0  # type: ignore[index]
    with pytest.raises(TypeError):
        recipe["kappa_rule"] = "gradient"  # type: ignore[index]
    assert recipe_options("wcsac", "dynamic")["pid"]["ki"] == 0.0


def test_one_constraint_is_not_shared_by_two_losses():
    parts = loss_parts(PAPER_OPTIONS)
    first = _loss(**parts)
    with pytest.raises(ValueError) as err:
        _loss(**parts)
    assert "\n" not in str(err.value)
    assert str(err.value).startswith("constraint is another WCSACLoss's")
    # a copy is the second loss's own, and training the first leaves it where it started
    second = _loss(**{**parts, "constraint": copy.deepcopy(parts["constraint"])})
    start = float(second.constraint.kappa)
    optim = torch.optim.Adam([first.constraint.kappa_raw], lr=0.5)
    for _ in range(3):
        optim.zero_grad()
        first(plain_batch(16, seed=1))["loss_kappa"].backward()
        optim.step()
    assert float(first.constraint.kappa) != start
    assert float(second.constraint.kappa) == start
    # the first loss may take its own constraint again (e.g. rebuilt in place)
    assert first.constraint is parts["constraint"]


def test_a_constraint_is_free_again_once_its_loss_is_gone():
    parts = loss_parts(PAPER_OPTIONS)
    loss = _loss(**parts)
    del loss
    import gc

    gc.collect()
    assert _loss(**parts).constraint is parts["constraint"]
