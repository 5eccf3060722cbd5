"""kappa_signal: κ held under d by the critic's Γ, the recent episodes' CVaR, or the larger."""

from __future__ import annotations

import math

import pytest
import torch
from _loss_helpers import make_batch, make_loss
from _training_helpers import compose_config
from tensordict import TensorDict

from wcsac_rl.objectives import EpisodeCostWindow, empirical_cvar
from wcsac_rl.training import ConfigError, make_trainer, validate_config
from wcsac_rl.training.checkpoint import load_checkpoint
from wcsac_rl.training.progress import read_progress

LIMIT = 15.0


def _ends(costs: list[list[float]], done: list[list[bool]]) -> TensorDict:
    """A collector-shaped batch [envs, time] with running episode costs and done flags."""
    cost = torch.tensor(costs).unsqueeze(-1)
    return TensorDict(
        {"next": {"episode_cost": cost, "done": torch.tensor(done).unsqueeze(-1)}},
        list(cost.shape[:2]),
    )


# ------------------------------------------------------------------ the window
def test_window_keeps_the_last_episodes_in_time_order_and_their_cvar():
    window = EpisodeCostWindow(0.5, window=3)
    assert math.isnan(window.value) and len(window) == 0
    # env 0 ends at t = 1 (cost 4) and t = 3 (cost 8); env 1 at t = 0 (cost 1) and t = 2 (2)
    batch = _ends(
        [[3.0, 4.0, 1.0, 8.0], [1.0, 0.0, 2.0, 0.0]],
        [[False, True, False, True], [True, False, True, False]],
    )
    assert window.add_episodes(batch) == 4
    # in time order the ends are 1, 4, 2, 8; a window of 3 keeps the last three
    assert window.costs == [4.0, 2.0, 8.0]
    assert window.value == empirical_cvar([4.0, 2.0, 8.0], 0.5) == 6.0
    assert window.add_episodes(_ends([[5.0]], [[False]])) == 0  # nothing ended
    assert window.costs == [4.0, 2.0, 8.0]


def test_attach_gives_every_row_the_value_and_nan_before_any_episode():
    window = EpisodeCostWindow(0.1, out_key="observed")
    rows = window.attach(make_batch(6))["observed"]
    assert rows.shape == (6, 1) and rows.isnan().all()
    window.add_episodes(_ends([[10.0, 30.0, 0.0]], [[True, True, True]]))
    rows = window.attach(make_batch(6))["observed"]
    assert torch.equal(rows, torch.full((6, 1), 30.0))


def test_window_state_round_trips_and_errors_change_nothing():
    window = EpisodeCostWindow(1.0, window=4)
    window.add_episodes(_ends([[2.0, 6.0]], [[True, True]]))
    restored = EpisodeCostWindow(1.0, window=4)
    restored.load_state_dict(window.state_dict())
    assert restored.costs == [2.0, 6.0] and restored.value == 4.0
    with pytest.raises(KeyError, match="RewardSum"):
        window.add_episodes(TensorDict({"next": {"done": torch.ones(2, 1, dtype=torch.bool)}}, [2]))
    with pytest.raises(ValueError, match="non-finite"):
        window.add_episodes(_ends([[math.nan]], [[True]]))
    assert window.costs == [2.0, 6.0] and window.value == 4.0
    for bad in (0, 2.5, True):
        with pytest.raises(ValueError, match="window"):
            EpisodeCostWindow(0.5, window=bad)
    with pytest.raises(ValueError, match="risk_level"):
        EpisodeCostWindow(0.0)


def test_a_test_window_floors_the_value_by_the_test_episodes_cvar():
    # training episodes by their mean (α = 1), test episodes by their CVaR_0.5
    window = EpisodeCostWindow(1.0, window=4, test_window=4, test_risk_level=0.5)
    assert window.test_costs == [] and math.isnan(window.value)
    window.add_test_costs([0.0, 40.0])  # before any training episode: the test CVaR alone
    assert window.value == 40.0
    window.add_episodes(_ends([[60.0, 20.0]], [[True, True]]))  # mean 40 = test CVaR 40
    assert window.value == 40.0
    window.add_test_costs([0.0, 0.0, 0.0])  # the test window keeps 40, 0, 0, 0: CVaR_0.5 20
    assert window.test_costs == [40.0, 0.0, 0.0, 0.0] and window.value == 40.0
    window.add_episodes(_ends([[0.0, 0.0]], [[True, True]]))  # mean 20 now: ties the test
    assert window.value == 20.0
    window.add_test_costs([90.0])  # 0, 0, 0, 90: the test CVaR_0.5 (45) is the larger
    assert window.value == 45.0
    restored = EpisodeCostWindow(1.0, window=4, test_window=4, test_risk_level=0.5)
    restored.load_state_dict(window.state_dict())
    assert restored.test_costs == [0.0, 0.0, 0.0, 90.0] and restored.value == 45.0
    with pytest.raises(ValueError, match="non-finite"):
        window.add_test_costs([1.0, math.inf])
    assert window.value == 45.0 and window.test_costs == [0.0, 0.0, 0.0, 90.0]
    with pytest.raises(RuntimeError, match="test_window=0"):
        EpisodeCostWindow(1.0).add_test_costs([1.0])
    for bad in (-1, 1.5, True):
        with pytest.raises(ValueError, match="test_window"):
            EpisodeCostWindow(1.0, test_window=bad)
    # a window saved before test windows existed restores with an empty one
    old = EpisodeCostWindow(1.0, window=4, test_window=4)
    old.load_state_dict({"costs": [3.0, 5.0], "window": 4, "risk_level": 1.0})
    assert old.test_costs == [] and old.value == 4.0


def _ends_with_lengths(costs: list[float], lengths: list[int]) -> TensorDict:
    """One env's batch in which each episode ends at its own step: cost and length."""
    n = len(costs)
    return TensorDict(
        {
            "next": {
                "episode_cost": torch.tensor(costs).reshape(1, n, 1),
                "done": torch.ones(1, n, 1, dtype=torch.bool),
                "step_count": torch.tensor(lengths).reshape(1, n, 1),
            }
        },
        [1, n],
    )


def test_a_rate_window_holds_short_episodes_to_the_rate_of_full_ones():
    window = EpisodeCostWindow(1.0, window=3, horizon=1000)
    # 1000 steps costing 30, 100 costing 3, 100 costing 0: 33 over 1200 steps
    window.add_episodes(_ends_with_lengths([30.0, 3.0, 0.0], [1000, 100, 100]))
    assert window.lengths == [1000.0, 100.0, 100.0]
    assert window.value == pytest.approx(1000 * 33 / 1200)  # 27.5; their mean is 11
    window.add_episodes(_ends_with_lengths([2.0], [50]))  # the first leaves the window
    assert window.value == pytest.approx(1000 * 5 / 250)  # 20: 2 in 50 steps is 40 per 1000
    # full-length episodes: the rate is their mean
    full = EpisodeCostWindow(1.0, window=4, horizon=1000)
    full.add_episodes(_ends_with_lengths([10.0, 0.0, 50.0], [1000, 1000, 1000]))
    assert full.value == pytest.approx(20.0)
    restored = EpisodeCostWindow(1.0, window=3, horizon=1000)
    restored.load_state_dict(window.state_dict())
    assert restored.value == window.value and restored.lengths == window.lengths
    # a window saved without lengths: its episodes count as full ones (their mean)
    restored.load_state_dict({"costs": [6.0, 0.0], "window": 3, "risk_level": 1.0})
    assert restored.value == pytest.approx(3.0)
    with pytest.raises(KeyError, match="step_count"):
        window.add_episodes(_ends([[1.0]], [[True]]))
    with pytest.raises(ValueError, match="lengths must be >= 1"):
        window.add_episodes(_ends_with_lengths([1.0], [0]))
    assert window.value == pytest.approx(20.0)
    with pytest.raises(ValueError, match="risk_level must be 1"):
        EpisodeCostWindow(0.1, horizon=1000)
    with pytest.raises(ValueError, match="horizon"):
        EpisodeCostWindow(1.0, horizon=0)


def test_for_loss_reads_the_rate_over_the_loss_episode_limit():
    loss = make_loss(risk_level=0.1, kappa_states="initial", max_episode_steps=200)
    window = EpisodeCostWindow.for_loss(loss, statistic="rate")
    assert window.horizon == 200 and window.risk_level == 1.0


def test_for_loss_follows_the_loss_s_episode_cvar_key_set_after_it():
    loss = make_loss(risk_level=0.1, kappa_states="initial", kappa_signal="max")
    window = EpisodeCostWindow.for_loss(loss)
    loss.set_keys(episode_cvar="held")
    window.add_episodes(_ends_with_lengths([4.0, 2.0], [10, 10]))
    batch = window.attach(TensorDict({}, [3]))
    assert window.out_key == "held" and set(batch.keys()) == {"held"}
    assert batch["held"].squeeze(-1).tolist() == [4.0] * 3  # the worst of two at α = 0.1
    assert EpisodeCostWindow(0.5, out_key="mine").out_key == "mine"  # its own: kept


# -------------------------------------------------------------------- the loss
def _kappa_grad(signal: str, episode_cvar: float | None, seed: int = 0):
    """∂loss_kappa/∂κ_raw and the loss outputs on a batch with start states."""
    loss = make_loss(
        risk_level=0.1,
        kappa_states="initial",
        kappa_statistic="tail",
        cost_limit=LIMIT,
        kappa_signal=signal,
        seed=seed,
    )
    batch = make_batch(32, initial=True, seed=seed)
    if episode_cvar is not None:
        batch["episode_cvar"] = torch.full((32, 1), episode_cvar)
    out = loss(batch)
    out["loss_kappa"].backward()
    return loss.kappa_raw.grad.item(), out, torch.sigmoid(loss.kappa_raw.detach()).item()


@pytest.mark.parametrize("episodes", [0.0, 3.0, 40.0])
def test_the_kappa_gradient_holds_the_chosen_signal_under_the_limit(episodes):
    grad_critic, out, dkappa = _kappa_grad("critic", None)
    critic = out["cvar"].item()  # the critic's tail CVaR at the start states
    grad_max, out_max, _ = _kappa_grad("max", episodes)
    grad_episodes, out_ep, _ = _kappa_grad("episodes", episodes)
    # ∂/∂raw of softplus(raw)·(d − signal) = sigmoid(raw)·(d − signal); the magnitudes
    # are ≤ 40, so float32 rounding stays far below 1e-4 relative
    assert grad_critic == pytest.approx(dkappa * (LIMIT - critic), rel=1e-4, abs=1e-5)
    assert grad_max == pytest.approx(dkappa * (LIMIT - max(critic, episodes)), rel=1e-4, abs=1e-5)
    assert grad_episodes == pytest.approx(dkappa * (LIMIT - episodes), rel=1e-4, abs=1e-5)
    # the logged cvar stays the critic's; the episodes' value is logged beside it
    assert out_max["cvar"].item() == out_ep["cvar"].item() == critic
    assert out_max["episode_cvar"].item() == out_ep["episode_cvar"].item() == episodes
    assert out_max["constraint_cvar"].item() == pytest.approx(max(critic, episodes), rel=1e-6)
    assert out_ep["constraint_cvar"].item() == episodes
    assert "episode_cvar" not in out.keys() and "constraint_cvar" not in out.keys()


def test_before_any_episode_ends_both_signals_fall_back_to_the_critic():
    grad_critic, _, _ = _kappa_grad("critic", None)
    for signal in ("max", "episodes"):
        grad, out, _ = _kappa_grad(signal, math.nan)
        assert grad == grad_critic and math.isnan(out["episode_cvar"].item())


def test_the_actor_and_critics_do_not_see_the_episode_signal():
    """Only κ's gradient (and the damping term, off here) depends on kappa_signal."""
    losses = {}
    for signal in ("critic", "max"):
        loss = make_loss(
            risk_level=0.1, kappa_states="initial", cost_limit=LIMIT, kappa_signal=signal
        )
        batch = make_batch(16, initial=True)
        batch["episode_cvar"] = torch.full((16, 1), 99.0)
        out = loss(batch)
        sum(v for k, v in out.items() if k.startswith("loss_")).backward()
        losses[signal] = loss
    for (name, p), (_, q) in zip(
        losses["critic"].named_parameters(), losses["max"].named_parameters(), strict=True
    ):
        if name == "constraint.kappa_raw":
            assert not torch.equal(p.grad, q.grad)
        elif p.grad is not None:
            assert torch.equal(p.grad, q.grad), name


def test_damping_uses_the_signal_kappa_sees():
    grads = {}
    for value in (0.0, 99.0):
        loss = make_loss(
            risk_level=0.1,
            kappa_states="initial",
            cost_limit=LIMIT,
            kappa_signal="episodes",
            damp_scale=1.0,
        )
        batch = make_batch(16, initial=True)
        batch["episode_cvar"] = torch.full((16, 1), value)
        loss(batch)["loss_actor"].backward()
        grads[value] = [p.grad.clone() for p in loss.actor_network_params.values(True, True)]
    assert any(not torch.equal(a, b) for a, b in zip(grads[0.0], grads[99.0]))


def test_loss_refuses_bad_signals_and_a_missing_entry_with_a_clear_error():
    with pytest.raises(ValueError, match="kappa_signal must be one of"):
        make_loss(kappa_states="initial", kappa_signal="observed")
    with pytest.raises(ValueError, match="kappa_signal=max needs kappa_states=initial"):
        make_loss(kappa_states="replay", kappa_signal="max")
    loss = make_loss(kappa_states="initial", kappa_signal="max")
    with pytest.raises(KeyError, match="EpisodeCostWindow"):
        loss(make_batch(8, initial=True))
    window = EpisodeCostWindow.for_loss(loss)  # the empirical CVaR_α by default
    assert window.risk_level == loss.risk_level and window.out_key == "episode_cvar"
    window = EpisodeCostWindow.for_loss(loss, statistic="mean")
    assert window.risk_level == 1.0
    with pytest.raises(ValueError, match="statistic must be one of"):
        EpisodeCostWindow.for_loss(loss, statistic="median")


# ----------------------------------------------------------------- the trainer
def test_config_validation_names_the_option():
    for overrides, message in (
        (("algo.kappa_signal=observed",), "algo.kappa_signal must be one of critic, max"),
        (("algo.kappa_signal=max", "algo.kappa_states=replay"), "needs algo.kappa_states=initial"),
        (("algo.kappa_signal=max", "algo.kappa_episode_window=0"), "kappa_episode_window"),
        (("algo.kappa_signal=max", "algo.kappa_test_window=-1"), "algo.kappa_test_window must"),
        (("algo.kappa_signal=critic", "algo.kappa_test_window=5"), "needs algo.kappa_signal=max"),
        (
            ("algo.kappa_signal=max", "algo.kappa_test_window=5", "eval_episodes=0"),
            "eval_episodes=0 runs none",
        ),
    ):
        with pytest.raises(ConfigError, match=message):
            validate_config(compose_config("env=tiny", *overrides))


def test_trainer_feeds_recent_episode_costs_to_kappa_and_resumes_the_window(tmp_path):
    options = ("env=tiny", "algo.kappa_signal=max", "algo.kappa_episode_window=3")
    run_dir = tmp_path / "run"
    first = make_trainer(compose_config(*options), run_dir)
    try:
        first.run()
        window = first.episode_window
        costs = window.costs
    finally:
        first.close()
    assert len(costs) == 3  # 800 frames of 100-step episodes: 8 ended, the last 3 kept
    assert window.value == empirical_cvar(costs, 0.5)
    progress = read_progress(run_dir / "progress.csv")
    logged = progress["loss/episode_cvar"]
    assert all(0.0 <= v <= max(progress["train/episode_cost"]) + 1e-6 for v in logged)
    # the slack is the gap κ saw: to the larger of the critic's and the episodes' CVaR
    for held, critic, slack, limit in zip(
        progress["loss/constraint_cvar"],
        progress["loss/cvar"],
        progress["loss/constraint_slack"],
        progress["loss/cost_threshold"],
    ):
        assert held >= critic - 1e-4 * max(1.0, abs(critic))
        assert slack == pytest.approx(limit - held)
    assert load_checkpoint(first.checkpoint_path)["learner"]["episode_window"]["costs"] == costs
    resumed = make_trainer(
        compose_config(*options, "total_frames=1200", f"resume={run_dir}"), run_dir
    )
    try:
        assert resumed.episode_window.costs == costs
        assert resumed.episode_window.value == window.value
    finally:
        resumed.close()


def test_trainer_feeds_the_test_episodes_to_the_test_window_and_resumes_it(tmp_path):
    options = (
        "env=tiny",
        "algo.kappa_signal=max",
        "algo.kappa_test_window=2",
        "eval_episodes=1",
        "epoch_frames=200",
    )
    run_dir = tmp_path / "run"
    first = make_trainer(compose_config(*options), run_dir)
    try:
        first.run()
        window = first.episode_window
    finally:
        first.close()
    progress = read_progress(run_dir / "progress.csv")
    # one test episode per epoch, the window keeps the last two epochs' costs
    assert window.test_costs == progress["eval/episode_cost"][-2:]
    assert window.value == max(
        empirical_cvar(window.costs, 0.5), empirical_cvar(window.test_costs, 0.5)
    )
    saved = load_checkpoint(first.checkpoint_path)["learner"]["episode_window"]
    assert saved["test_costs"] == window.test_costs
    resumed = make_trainer(
        compose_config(*options, "total_frames=1200", f"resume={run_dir}"), run_dir
    )
    try:
        assert resumed.episode_window.test_costs == window.test_costs
    finally:
        resumed.close()


def test_an_iqn_critic_takes_the_same_signal():
    loss = make_loss(
        kind="iqn", risk_level=0.1, kappa_states="initial", cost_limit=LIMIT, kappa_signal="max"
    )
    batch = make_batch(16, initial=True)
    batch["episode_cvar"] = torch.full((16, 1), 50.0)
    out = loss(batch)
    out["loss_kappa"].backward()
    dkappa = torch.sigmoid(loss.kappa_raw.detach()).item()
    critic = out["cvar"].item()
    assert critic < 50.0  # a freshly initialised critic: the episodes are the larger
    assert loss.kappa_raw.grad.item() == pytest.approx(dkappa * (LIMIT - 50.0), rel=1e-4)
