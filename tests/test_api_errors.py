"""A wrong argument to the library's classes and functions is one line naming the
argument and what it accepts, raised before anything changes: recipes, constraints,
ensembles of safety critics, the batch the loss reads, its keys and its state dict."""

from __future__ import annotations

import pytest
import torch
from _loss_helpers import plain_batch
from torchrl.data import Bounded

from wcsac_rl import WCSACLoss
from wcsac_rl.modules import make_actor, make_qvalue, make_safety_critic
from wcsac_rl.objectives import PAPER_OPTIONS, loss_parts, recipe_options
from wcsac_rl.objectives.constraint import GradientLagrangian, PIDGains, PIDLagrangian

SPEC = Bounded(-1.0, 1.0, shape=(2,))


def _loss(safety, members: int = 1, **keywords) -> WCSACLoss:
    torch.manual_seed(0)
    parts = loss_parts({**PAPER_OPTIONS, "num_safety_nets": members})
    return WCSACLoss(
        make_actor(4, SPEC, width=8), make_qvalue(4, 2, width=8), safety,
        risk_level=0.5, cost_limit=15.0, action_spec=SPEC, **{**parts, **keywords},
    )  # fmt: skip


def _one_line(excinfo, *words: str) -> str:
    message = str(excinfo.value)
    assert "\n" not in message, message
    for word in words:
        assert word in message, message
    return message


def _critics(*kinds_and_widths):
    torch.manual_seed(1)
    return [make_safety_critic(4, 2, kind=kind, width=width) for kind, width in kinds_and_widths]


def test_a_recipe_name_that_is_not_a_string_names_the_algorithms():  # R4
    with pytest.raises(ValueError) as excinfo:
        recipe_options(["wcsac"])
    _one_line(excinfo, "no recipe for algorithm", "wcsac, wcsac_paper")


def test_loss_parts_takes_a_mapping_not_a_recipe_name():  # R14
    with pytest.raises(TypeError) as excinfo:
        loss_parts("paper")
    _one_line(excinfo, "loss_parts takes a recipe", "PAPER_OPTIONS", "got str 'paper'")


@pytest.mark.parametrize(
    ("value", "shown"), [("abc", "'abc'"), (-1.0, "-1.0"), (0.0, "0.0"), ("0.1", "'0.1'")]
)
def test_alpha_init_that_is_not_a_positive_number_is_named(value, shown):  # R8, R9, L19
    parts = loss_parts({**PAPER_OPTIONS, "alpha_init": value})  # (the loss checks it)
    with pytest.raises(ValueError) as excinfo:
        _loss(make_safety_critic(4, 2, width=8), **{"alpha_init": parts["alpha_init"]})
    _one_line(excinfo, f"alpha_init must be in (0, 1e+06] (a number), got {shown}")


@pytest.mark.parametrize(
    ("build", "words"),
    [
        (lambda: GradientLagrangian(kappa_init="0.5"), "kappa_init must be in [0, 1e+06]"),
        (lambda: GradientLagrangian(kappa_init=float("inf")), "got inf"),
        (lambda: GradientLagrangian(kappa_init=1e300), "got 1e+300"),
        (lambda: GradientLagrangian(damp_scale=float("inf")), "damp_scale must be in"),
        (lambda: PIDLagrangian(kappa_init="x"), "kappa_init must be in [0, 1e+06]"),
    ],
)
def test_a_constraint_built_directly_checks_its_numbers(build, words):  # R25, R26, R27
    with pytest.raises(ValueError) as excinfo:
        build()
    _one_line(excinfo, words)


def test_pid_gains_given_as_a_dict_name_the_class_to_use():  # R29
    with pytest.raises(TypeError) as excinfo:
        PIDLagrangian(gains={"kp": 1.0})
    _one_line(excinfo, "gains must be a PIDGains", "got dict")
    assert PIDLagrangian(gains=PIDGains(kp=1.0)).gains.kp == 1.0


@pytest.mark.parametrize(
    ("members", "words"),
    [
        ((("iqn", 8), ("gaussian", 8)), "critic 1 of the ensemble is not the same network"),
        ((("iqn", 8), ("iqn", 16)), "has module.features.0.weight of shape [16, 6], critic 0"),
    ],
)
def test_an_ensemble_of_unlike_critics_is_named(members, words):  # R37, R38
    with pytest.raises(ValueError) as excinfo:
        _loss(_critics(*members), members=2)
    _one_line(excinfo, words)


def test_a_reward_of_another_shape_than_done_is_named():  # L8
    loss = _loss(make_safety_critic(4, 2, width=8))
    batch = plain_batch(8)
    batch["next", "reward"] = batch["next", "reward"].squeeze(-1)
    before = {k: v.clone() for k, v in loss.state_dict().items()}
    with pytest.raises(ValueError) as excinfo:
        loss(batch)
    _one_line(excinfo, "('next', 'reward') has shape [8], ('next', 'done') [8, 1]")
    assert all(torch.equal(before[k], v) for k, v in loss.state_dict().items())


def test_a_batch_on_another_device_is_named():  # L12
    loss = _loss(make_safety_critic(4, 2, width=8))
    with pytest.raises(ValueError) as excinfo:
        loss(plain_batch(8).to("meta"))
    _one_line(excinfo, "'observation' is on meta", "parameters on cpu", ".to('cpu')")


def test_a_misspelt_key_names_the_loss_keys_and_the_closest():  # L15
    loss = _loss(make_safety_critic(4, 2, width=8))
    with pytest.raises(ValueError) as excinfo:
        loss.set_keys(costt="x")
    message = _one_line(excinfo, "'costt' is not a key of the loss", "did you mean 'cost'?")
    assert len(message) < 400
    assert loss.tensor_keys.cost == "cost"
    loss.set_keys(cost="my_cost")
    assert loss.tensor_keys.cost == "my_cost"


def test_a_state_dict_of_another_ensemble_size_is_named():  # L22
    four = _loss(_critics(*[("gaussian", 8)] * 4), members=4)
    two = _loss(_critics(*[("gaussian", 8)] * 2), members=2)
    before = {k: v.clone() for k, v in two.state_dict().items()}
    with pytest.raises(ValueError) as excinfo:
        two.load_state_dict(four.state_dict())
    _one_line(excinfo, "has shape [4, 8, 6] in the state dict, [2, 8, 6] in this loss")
    assert all(torch.equal(before[k], v) for k, v in two.state_dict().items())
    two.load_state_dict(_loss(_critics(*[("gaussian", 8)] * 2), members=2).state_dict())


def test_an_action_spec_whose_high_is_not_above_its_low_is_refused_by_make_actor():
    spec = Bounded(torch.tensor([-1.0, 2.0]), torch.tensor([1.0, 2.0]), shape=(2,))
    with pytest.raises(ValueError) as excinfo:
        make_actor(4, spec, width=8)
    _one_line(excinfo, "high is above its low", "low=[-1.0, 2.0]")
