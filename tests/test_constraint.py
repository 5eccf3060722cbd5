"""The constraint part: the gradient rule and the PID Lagrangian, alone and wired into
every Lagrangian algorithm (WCSAC Gaussian, WCSAC IQN, SAC-Lag)."""

from __future__ import annotations

import csv
import math
import re
import subprocess
import sys

import pytest
import torch
from _loss_helpers import make_batch, make_loss
from _training_helpers import ROOT, TINY_CLI, compose_config

from wcsac_rl.objectives.constraint import (
    GradientLagrangian,
    PIDGains,
    PIDLagrangian,
    make_constraint,
)
from wcsac_rl.training import ConfigError, make_trainer, validate_config
from wcsac_rl.training.builders import make_optimizers

D = torch.tensor(15.0)


def _gains(**gains) -> PIDGains:
    """PID gains with every term off unless given (the analytic sequences below)."""
    return PIDGains(**{"kp": 0.0, "ki": 0.0, "kd": 0.0, "p_ema": 0.0, "d_ema": 0.0, **gains})


def _kappas(pid: PIDLagrangian, signals: list[float]) -> list[float]:
    out = []
    for x in signals:
        pid.step(torch.tensor(x), D)
        out.append(float(pid.kappa))
    return out


# ------------------------------------------------------------------ the PID rule
def test_proportional_term_answers_at_once_and_stops_at_zero():
    pid = PIDLagrangian(0.0, _gains(kp=0.1, ki=0.0))
    # 10 over d: κ = 0.1 · 10; 5 under: 0.1 · (−5) clipped to 0; at d: 0
    assert _kappas(pid, [25.0, 10.0, 15.0, 35.0]) == pytest.approx([1.0, 0.0, 0.0, 2.0])


def test_proportional_term_reads_an_ema_of_the_error():
    pid = PIDLagrangian(0.0, _gains(kp=1.0, ki=0.0, p_ema=0.5))
    # P ← 0.5 P + 0.5 e with e = 10: 5, 7.5, 8.75
    assert _kappas(pid, [25.0, 25.0, 25.0]) == pytest.approx([5.0, 7.5, 8.75])


def test_integral_starts_at_kappa_init_and_is_clipped_both_ways():
    pid = PIDLagrangian(0.5, _gains(ki=0.1, max_kappa=2.0))
    assert float(pid.kappa) == 0.5  # where the gradient rule's κ starts too
    # e = +10 per step: I = 1.5, 2 (clipped: anti-windup), 2, 2
    assert _kappas(pid, [25.0] * 4) == pytest.approx([1.5, 2.0, 2.0, 2.0])
    # e = −10: it unwinds at once (without the clip it would first fall from 4.5) ...
    assert _kappas(pid, [5.0] * 3) == pytest.approx([1.0, 0.0, 0.0])
    # ... and never goes below 0: one step over d brings κ back at once
    assert _kappas(pid, [25.0]) == pytest.approx([1.0])


def test_derivative_term_sees_a_rise_over_exactly_the_delay_and_ignores_falls():
    pid = PIDLagrangian(0.0, _gains(ki=0.0, kd=1.0, d_delay=3))
    # signals stay under d (no P or I); a step from 0 to 5 is a rise of 5 for the
    # d_delay = 3 steps whose comparison reaches back before it, then it is old news
    kappas = _kappas(pid, [0.0, 0.0, 0.0, 5.0, 5.0, 5.0, 5.0, 5.0, 0.0, 0.0])
    assert kappas == pytest.approx([0, 0, 0, 5, 5, 5, 0, 0, 0, 0])


def test_derivative_term_waits_for_a_full_history():
    pid = PIDLagrangian(0.0, _gains(ki=0.0, kd=1.0, d_delay=4))
    # the first d_delay steps have nothing d_delay steps back: no derivative yet
    assert _kappas(pid, [0.0, 2.0, 4.0, 6.0, 8.0]) == pytest.approx([0, 0, 0, 0, 8.0])


def test_derivative_reads_an_ema_of_the_signal():
    pid = PIDLagrangian(0.0, _gains(ki=0.0, kd=1.0, d_delay=1, d_ema=0.5))
    # C starts at the first signal (0), then C ← 0.5 C + 0.5 x: 4, 6; rises 4, 2
    assert _kappas(pid, [0.0, 8.0, 8.0]) == pytest.approx([0.0, 4.0, 2.0])


def test_kappa_is_clipped_to_max_kappa():
    pid = PIDLagrangian(0.0, _gains(kp=1.0, ki=0.0, max_kappa=3.0))
    assert _kappas(pid, [115.0]) == [3.0]


def test_a_nan_signal_changes_nothing():
    pid = PIDLagrangian(0.5, _gains(kp=0.1, ki=0.1, kd=0.1, d_delay=2, p_ema=0.5))
    _kappas(pid, [20.0, 30.0])
    before = {k: v.clone() for k, v in pid.state_dict().items()}
    pid.step(torch.tensor(math.nan), D)
    for key, value in pid.state_dict().items():
        assert torch.equal(value, before[key]), key


def test_the_controller_state_survives_a_state_dict_round_trip():
    gains = PIDGains(kp=0.05, ki=0.01, kd=0.2, d_delay=3, p_ema=0.9, d_ema=0.5)
    first = PIDLagrangian(0.7, gains)
    signals = [3.0, 30.0, 12.0, 40.0, 18.0]
    _kappas(first, signals)
    second = PIDLagrangian(0.7, gains)
    second.load_state_dict(first.state_dict())
    assert _kappas(first, [25.0, 9.0, 50.0]) == _kappas(second, [25.0, 9.0, 50.0])


def test_pid_step_averages_a_batch_of_signals():
    pid = PIDLagrangian(0.0, _gains(kp=0.1, ki=0.0))
    pid.step(torch.tensor([[20.0], [30.0]]), D)
    assert float(pid.kappa) == pytest.approx(1.0)


@pytest.mark.parametrize(
    ("gains", "message"),
    [
        ({"kp": -0.1}, "pid.kp must be a finite number in [0, 1e+06]"),
        ({"ki": -1e-4}, "pid.ki must be a finite number in [0, 1e+06]"),
        ({"kd": math.inf}, "pid.kd must be a finite number in [0, 1e+06]"),
        ({"d_delay": 0}, "pid.d_delay must be an integer >= 1"),
        ({"d_delay": 2.5}, "pid.d_delay must be an integer >= 1"),
        ({"p_ema": 1.0}, "pid.p_ema must be in [0, 1)"),
        ({"d_ema": -0.1}, "pid.d_ema must be in [0, 1)"),
        ({"max_kappa": 0.0}, "pid.max_kappa must be a finite number in (0, 1e+06]"),
    ],
)
def test_bad_gains_are_refused_by_name(gains, message):
    with pytest.raises(ValueError, match=re.escape(message)):
        PIDGains(**gains)


def test_make_constraint_refuses_the_other_rules_options():
    with pytest.raises(
        ValueError, match=re.escape("kappa_rule must be one of gradient, pid, got 'lagrange'")
    ):
        make_constraint("lagrange", kappa_init=0.5)
    with pytest.raises(ValueError, match=re.escape("damp_scale=0.1 is the gradient rule's")):
        make_constraint("pid", kappa_init=0.5, damp_scale=0.1)
    with pytest.raises(ValueError, match=re.escape("pid gains apply to kappa_rule='pid' only")):
        make_constraint("gradient", kappa_init=0.5, pid={"kp": 1.0})
    with pytest.raises(
        ValueError, match=re.escape("kappa_init must be <= pid.max_kappa (1) with kappa_rule=pid")
    ):
        make_constraint("pid", kappa_init=5.0, pid={"max_kappa": 1.0})


# ------------------------------------------------------------- the gradient rule
@pytest.mark.parametrize("parametrization", ["softplus", "log"])
def test_gradient_rule_raises_kappa_while_the_signal_is_over(parametrization):
    constraint = GradientLagrangian(0.5, parametrization)
    assert float(constraint.kappa) == pytest.approx(0.5, rel=1e-6)
    constraint.loss(torch.tensor([25.0, 35.0]), D).mean().backward()
    # d/draw of κ · (d − x) = κ'(raw) · (d − x) < 0: descent raises κ
    slope = 0.5 if parametrization == "log" else 1 - math.exp(-0.5)  # κ'(raw)
    assert float(constraint.kappa_raw.grad) == pytest.approx(slope * (15.0 - 30.0), rel=1e-5)


def test_gradient_rule_damping_lowers_the_penalty_while_under():
    constraint = GradientLagrangian(0.5, damp_scale=0.1)
    weight = constraint.penalty_weight(torch.tensor([5.0, 15.0]), D)  # 5 under on average
    assert float(weight) == pytest.approx(0.5 - 0.1 * 5.0, rel=1e-6)


def _sgd_updates(constraint: GradientLagrangian, lr: float = 0.05):
    """``update(signal) -> κ``: one plain SGD step on the κ loss, then the constraint's
    projection, as the trainer does it (with Adam)."""
    optimizer = torch.optim.SGD(constraint.parameters(), lr=lr)

    def update(signal: float) -> float:
        optimizer.zero_grad()
        constraint.loss(torch.tensor([signal]), D).mean().backward()
        optimizer.step()
        constraint.step(torch.tensor(signal), D)
        return float(constraint.kappa)

    return update


def _kappa_slope(parametrization: str, kappa: float) -> float:
    """dκ/d(kappa_raw) at κ (float32 κ, as the module holds it)."""
    kappa32 = float(torch.tensor(kappa))
    return kappa32 if parametrization == "log" else 1 - math.exp(-kappa32)


@pytest.mark.parametrize("parametrization", ["softplus", "log"])
def test_kappa_max_bounds_kappa_without_winding_up(parametrization):
    """A long violation holds κ at the bound; once the signal is under the threshold κ
    falls at the very next step (``kappa_raw`` was projected, not left to wind up)."""
    constraint = GradientLagrangian(0.1, parametrization, kappa_max=0.2)
    update = _sgd_updates(constraint)
    kappas = [update(45.0) for _ in range(200)]  # 30 over: the plain rule would reach e^300
    assert max(kappas) == pytest.approx(0.2, rel=1e-6) and kappas[-1] == pytest.approx(0.2)
    raw_at_bound = float(constraint.kappa_raw.detach())
    assert raw_at_bound == pytest.approx(constraint._raw(0.2), rel=1e-6)
    # 30 under: one plain gradient step down from the bound, whatever the past
    expected_raw = raw_at_bound - 0.05 * _kappa_slope(parametrization, 0.2) * 30.0
    assert update(-15.0) < 0.2
    assert float(constraint.kappa_raw.detach()) == pytest.approx(expected_raw, rel=1e-5)


@pytest.mark.parametrize("parametrization", ["softplus", "log"])
def test_kappa_min_floors_kappa_and_the_climb_starts_from_the_floor(parametrization):
    """A long stretch under the threshold lowers κ to the floor and no further; the
    first violation after it raises ``kappa_raw`` by one plain step from the floor's
    raw value (it was projected, not left to decay)."""
    constraint = GradientLagrangian(0.5, parametrization, kappa_min=0.1)
    update = _sgd_updates(constraint)
    kappas = [update(0.0) for _ in range(500)]  # 15 under: the plain rule decays to ~0
    assert min(kappas) == pytest.approx(0.1, rel=1e-6) and kappas[-1] == pytest.approx(0.1)
    raw_at_floor = float(constraint.kappa_raw.detach())
    assert raw_at_floor == pytest.approx(constraint._raw(0.1), rel=1e-6)
    expected_raw = raw_at_floor + 0.05 * _kappa_slope(parametrization, 0.1) * 10.0  # 10 over
    assert update(25.0) > 0.1
    assert float(constraint.kappa_raw.detach()) == pytest.approx(expected_raw, rel=1e-5)


def test_pid_kappa_min_floors_the_output_while_the_integral_unwinds():
    """Under the threshold the PID's integral unwinds to 0 and its output would be 0;
    the floor holds κ there. It is a clip, not an offset: the first violation's P and I
    terms take over at once."""
    gains = PIDGains(kp=0.1, ki=0.01, p_ema=0.0, max_kappa=5.0)
    pid = PIDLagrangian(0.5, gains, kappa_min=0.3)
    for _ in range(100):
        pid.step(torch.tensor(5.0), D)  # 10 under
    assert float(pid.integral) == 0.0
    assert float(pid.kappa) == pytest.approx(0.3, rel=1e-6)
    pid.step(torch.tensor(35.0), D)  # 20 over: P 0.1·20 + I 0.01·20 (not + the floor)
    assert float(pid.kappa) == pytest.approx(2.0 + 0.2, rel=1e-6)


def test_pid_i_error_max_bounds_what_a_violation_adds_to_the_integral():
    """With ``i_error_max`` the integral adds at most ``ki · i_error_max`` per update: a
    window 45 over the threshold winds it up no faster than one 15 over, and a stretch
    of cost-free updates (error −15) takes off exactly what as many updates over put on
    when the bound is d. The P term still sees the whole error. Without the bound
    (the default) the integral adds the whole error."""
    gains = dict(kp=0.1, ki=0.01, p_ema=0.0, max_kappa=50.0)
    bounded = PIDLagrangian(0.1, PIDGains(i_error_max=15.0, **gains))
    plain = PIDLagrangian(0.1, PIDGains(**gains))
    for _ in range(10):
        bounded.step(torch.tensor(60.0), D)  # 45 over
        plain.step(torch.tensor(60.0), D)
    assert float(bounded.integral) == pytest.approx(0.1 + 10 * 0.01 * 15.0, rel=1e-5)
    assert float(plain.integral) == pytest.approx(0.1 + 10 * 0.01 * 45.0, rel=1e-5)
    # the output: P on the whole error (0.1 · 45) plus the bounded integral
    assert float(bounded.kappa) == pytest.approx(4.5 + 1.6, rel=1e-5)
    for _ in range(10):
        bounded.step(torch.tensor(0.0), D)  # 15 under: not clipped (a bound from above)
    assert float(bounded.integral) == pytest.approx(0.1, rel=1e-4)


@pytest.mark.parametrize("rule", ["gradient", "pid"])
@pytest.mark.parametrize("kappa_min", [-0.1, math.nan, math.inf, "0.1"])
def test_a_bad_kappa_min_is_refused_by_name(rule, kappa_min):
    with pytest.raises(
        ValueError, match=re.escape("kappa_min must be a finite number in [0, 1e+06]")
    ):
        make_constraint(rule, kappa_init=0.5, kappa_min=kappa_min)


@pytest.mark.parametrize(
    ("bounds", "raw_kappa", "bound", "signal"),
    [
        ({"kappa_init": 0.1, "kappa_max": 0.2}, 0.5, 0.2, 5.0),  # over the bound, 10 under
        ({"kappa_init": 0.5, "kappa_min": 0.1}, 0.02, 0.1, 25.0),  # under the floor, 10 over
    ],
)
def test_a_kappa_bound_reads_its_value_and_passes_the_gradient_beyond_it(
    bounds, raw_kappa, bound, signal
):
    """While ``kappa_raw`` is beyond a bound (at most one optimizer step, before the
    projection), κ reads the bound and the gradient is the bound's value through the
    identity: d/draw of κ · (d − x) with dκ/draw = κ for the log parametrization."""
    constraint = GradientLagrangian(parametrization="log", **bounds)
    with torch.no_grad():
        constraint.kappa_raw.fill_(math.log(raw_kappa))  # as after an optimizer step
    assert float(constraint.kappa) == pytest.approx(bound, rel=1e-6)
    constraint.loss(torch.tensor([signal]), D).mean().backward()
    assert float(constraint.kappa_raw.grad) == pytest.approx(bound * (15.0 - signal), rel=1e-5)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"kappa_init": 0.5, "kappa_max": 0.1}, "kappa_max must be a finite number >= kappa_init"),
        ({"kappa_init": 0.5, "kappa_max": math.inf}, "kappa_max must be null or in (0, 1e+06]"),
    ],
)
def test_bad_kappa_max_is_refused(kwargs, message):
    with pytest.raises(ValueError, match=re.escape(message)):
        make_constraint("gradient", **kwargs)
    with pytest.raises(ValueError, match=re.escape("kappa_max=0.1 bounds the gradient rule")):
        make_constraint("pid", kappa_init=0.05, kappa_max=0.1)


# --------------------------------------------------------- wired into the losses
LOSSES = {
    "wcsac": {"risk_level": 0.1},
    "wcsac_iqn": {"risk_level": 0.1, "kind": "iqn"},
    "sac_lag": {"risk_level": 1.0, "variance": False},
}


@pytest.mark.parametrize("name", sorted(LOSSES))
def test_pid_loss_has_no_kappa_term_or_parameter_and_steps_in_training_mode(name):
    loss = make_loss(
        **LOSSES[name],
        kappa_rule="pid",
        pid=_gains(kp=0.1),
        kappa_init=0.0,
        cost_threshold=0.0,
    )
    assert loss.kappa_rule == "pid"
    assert not any("kappa" in n for n, _ in loss.named_parameters())
    out = loss(make_batch())
    assert "loss_kappa" not in out.keys() and "loss_kappa" not in loss.out_keys
    # this forward's actor loss used κ = 0; then the controller stepped on its signal
    # (Γ, positive, over the threshold 0): κ = kp · Γ
    assert float(out["kappa"]) == 0.0
    assert float(loss.kappa) == pytest.approx(0.1 * float(out["cvar"]), rel=1e-5)
    assert float(loss.kappa) > 0
    assert int(loss.constraint.steps) == 1
    # the next forward's actor loss sees the new κ; eval mode freezes the controller
    loss.eval()
    frozen = float(loss.kappa)
    after = loss(make_batch(seed=1))
    assert float(after["kappa"]) == frozen == float(loss.kappa)
    assert int(loss.constraint.steps) == 1


@pytest.mark.parametrize("name", sorted(LOSSES))
def test_pid_loss_reports_the_controllers_integral_and_error_before_its_step(name):
    gains = _gains(kp=0.2, ki=0.01, p_ema=0.5)
    loss = make_loss(**LOSSES[name], kappa_rule="pid", pid=gains, kappa_init=0.3)
    assert {"kappa_integral", "kappa_error"} <= set(loss.out_keys)
    first = loss(make_batch())
    # before the first step: the integral is kappa_init, the error's EMA 0, κ = I
    assert float(first["kappa_integral"]) == pytest.approx(0.3)
    assert float(first["kappa_error"]) == 0.0
    assert float(first["kappa"]) == pytest.approx(0.3)
    # the step used the signal against the threshold: e = Γ − d
    error = float(first["cvar"]) - float(first["cost_threshold"])
    second = loss(make_batch(seed=1))
    assert float(second["kappa_error"]) == pytest.approx(0.5 * error, rel=1e-5, abs=1e-6)
    integral = min(max(0.3 + 0.01 * error, 0.0), gains.max_kappa)
    assert float(second["kappa_integral"]) == pytest.approx(integral, rel=1e-5, abs=1e-6)
    # κ is the sum of the two terms (no derivative gain), clipped at 0
    expected = max(0.2 * float(second["kappa_error"]) + float(second["kappa_integral"]), 0.0)
    assert float(second["kappa"]) == pytest.approx(expected, rel=1e-5, abs=1e-6)


def test_gradient_loss_reports_no_controller_state():
    loss = make_loss(risk_level=0.5)
    assert not {"kappa_integral", "kappa_error"} & set(loss.out_keys)
    assert not {"kappa_integral", "kappa_error"} & set(loss(make_batch()).keys())


def test_the_pid_kappa_weighs_the_actors_cost_term():
    batch = make_batch()
    actors = []
    for kappa in (0.0, 2.0):
        loss = make_loss(risk_level=0.1, kappa_rule="pid", kappa_init=kappa)
        loss.eval()
        torch.manual_seed(0)
        actors.append(loss.actor_loss(batch))
    (loss_0, meta), (loss_2, _) = actors
    # same networks and draws: the actor losses differ by exactly κ · mean Γ_π
    gamma = meta["cvar_policy"].mean()
    assert float(loss_2 - loss_0) == pytest.approx(2.0 * float(gamma), rel=1e-4)


def test_gradient_loss_keeps_its_kappa_parameter_and_forward_leaves_kappa_alone():
    loss = make_loss(risk_level=0.5)
    before = float(loss.kappa)
    out = loss(make_batch())
    assert "loss_kappa" in out.keys()
    assert float(loss.kappa) == before
    assert [n for n, _ in loss.named_parameters() if "kappa" in n] == ["constraint.kappa_raw"]


def test_a_state_dict_saved_before_the_split_still_loads():
    loss = make_loss(risk_level=0.5)
    state = loss.state_dict()
    state["kappa_raw"] = state.pop("constraint.kappa_raw").clone().fill_(1.25)
    loss.load_state_dict(state)
    assert float(loss.kappa_raw.detach()) == 1.25


@pytest.mark.parametrize(
    "overrides",
    [["algo=wcsac"], ["algo=wcsac", "algo.safety_critic=iqn"], ["algo=sac_lag"]],
    ids=["wcsac", "wcsac_iqn", "sac_lag"],
)
def test_kappa_rule_pid_is_selectable_for_every_lagrangian_algorithm(tmp_path, overrides):
    cfg = compose_config(
        "env=tiny", *overrides, "algo.kappa_rule=pid", "algo.pid.kp=0.5", "total_frames=600"
    )
    trainer = make_trainer(cfg, tmp_path / "run")
    try:
        assert trainer.loss.kappa_rule == "pid"
        assert "kappa" not in make_optimizers(cfg, trainer.loss)
        assert "kappa" not in trainer.optimizers
        trainer.run()
        kappa = trainer.loss.constraint
        assert int(kappa.steps) == trainer.updates > 0  # one controller step per update
    finally:
        trainer.close()


def test_a_pid_run_logs_the_controllers_integral_and_error(tmp_path):
    cfg = compose_config("env=tiny", "algo.kappa_rule=pid", "algo.pid.ki=0.001")
    trainer = make_trainer(cfg, tmp_path / "run")
    try:
        trainer.run()
        integral = float(trainer.loss.constraint.integral)
    finally:
        trainer.close()
    rows = list(csv.DictReader((tmp_path / "run" / "progress.csv").open()))
    logged = [float(r["loss/kappa_integral"]) for r in rows]
    assert all(math.isfinite(v) for v in logged + [float(r["loss/kappa_error"]) for r in rows])
    # each epoch's mean over its updates lies within the integral's clip range, and the
    # integral moved away from where it started (kappa_init = log 2) by ki·e per update
    assert all(0.0 <= v <= 100.0 for v in logged)
    assert integral != pytest.approx(math.log(2.0), abs=1e-9)


def test_the_trainer_steps_the_pid_and_resume_continues_its_state(tmp_path):
    run = tmp_path / "run"
    cfg = compose_config("env=tiny", "algo.kappa_rule=pid", "algo.pid.ki=0.001")
    trainer = make_trainer(cfg, run)
    try:
        trainer.run()
        state = {k: v.clone() for k, v in trainer.loss.constraint.state_dict().items()}
    finally:
        trainer.close()
    resumed = make_trainer(
        compose_config("env=tiny", "algo.kappa_rule=pid", "algo.pid.ki=0.001", f"resume={run}"),
        run,
    )
    try:
        for key, value in resumed.loss.constraint.state_dict().items():
            assert torch.equal(value, state[key]), key
    finally:
        resumed.close()


@pytest.mark.parametrize(
    ("override", "message"),
    [
        (
            "algo.kappa_rule=lagrange",
            "algo.kappa_rule must be one of gradient, pid, got 'lagrange'",
        ),
        ("algo.pid.kp=-0.5", "algo.pid.kp must be a finite number in [0, 1e+06], got -0.5"),
        ("algo.pid.kd=abc", "algo.pid.kd must be a finite number in [0, 1e+06], got 'abc'"),
        ("algo.pid.d_delay=0", "algo.pid.d_delay must be an integer >= 1"),
        ("algo.pid.max_kappa=-1", "algo.pid.max_kappa must be a finite number in (0, 1e+06]"),
        (
            "algo.pid.i_error_max=0",
            "algo.pid.i_error_max must be null or a finite number in (0, 1e+06], got 0",
        ),
        ("+algo.pid.kq=1", "unknown PID option algo.pid.kq"),
    ],
)
def test_bad_pid_config_is_one_line_naming_the_option(tmp_path, override, message):
    with pytest.raises(ConfigError, match=re.escape(message)):
        make_trainer(compose_config("env=tiny", "algo.kappa_rule=pid", override), tmp_path / "r")
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (
            ["algo.kappa_max=0.1"],
            "algo.kappa_max must be a finite number >= algo.kappa_init (0.693147, where κ "
            "starts), got 0.1",
        ),
        (["algo.kappa_max=-1"], "algo.kappa_max must be null or in (0, 1e+06] (a number), got -1"),
        (["algo.kappa_min=-0.1"], "algo.kappa_min must be a finite number in [0, 1e+06], got -0.1"),
        (["algo.kappa_min=inf"], "algo.kappa_min must be a finite number in [0, 1e+06], got inf"),
        (
            ["algo.kappa_rule=pid", "algo.kappa_init=0.1", "algo.kappa_max=0.1"],
            "algo.kappa_max=0.1 bounds the gradient rule's κ; with algo.kappa_rule=pid the "
            "bound is algo.pid.max_kappa",
        ),
        (
            ["algo.kappa_init=0"],
            "algo.kappa_init must be > 0 with the gradient rule (κ is softplus or exp of a "
            "parameter; algo.kappa_rule=pid may start at 0), got 0",
        ),
        (["algo.kappa_rule=pid", "algo.kappa_init=-1"], "algo.kappa_init must be in [0, 1e+06]"),
    ],
)
def test_bad_kappa_max_config_is_one_line_naming_the_option(tmp_path, overrides, message):
    with pytest.raises(ConfigError, match=re.escape(message)):
        make_trainer(compose_config("env=tiny", *overrides), tmp_path / "r")
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize("algo", ["wcsac", "sac_lag"])
def test_kappa_bounds_reach_the_loss_constraint(tmp_path, algo):
    cfg = compose_config(
        "env=tiny",
        f"algo={algo}",
        "algo.kappa_init=0.05",
        "algo.kappa_max=0.25",
        "algo.kappa_min=0.01",
    )
    trainer = make_trainer(cfg, tmp_path / "r")
    try:
        assert trainer.loss.constraint.kappa_max == 0.25
        assert trainer.loss.constraint.kappa_min == 0.01
    finally:
        trainer.close()
    pid = make_trainer(
        compose_config("env=tiny", f"algo={algo}", "algo.kappa_rule=pid", "algo.kappa_min=0.02"),
        tmp_path / "p",
    )
    try:
        assert pid.loss.constraint.kappa_min == 0.02
    finally:
        pid.close()
    # a PID controller may start at κ = 0 from the config as from the constructor
    zero = make_trainer(
        compose_config("env=tiny", f"algo={algo}", "algo.kappa_rule=pid", "algo.kappa_init=0"),
        tmp_path / "z",
    )
    try:
        assert float(zero.loss.constraint.kappa) == 0.0
    finally:
        zero.close()


def test_a_delay_longer_than_the_run_is_refused(tmp_path):
    # 800 frames, 200 of them random, 0.25 updates per frame: 150 updates
    cfg = compose_config(
        "env=tiny", "algo.kappa_rule=pid", "algo.pid.kd=0.1", "algo.pid.d_delay=151"
    )
    with pytest.raises(
        ConfigError, match=re.escape("d_delay=151 updates is longer than the run's 150")
    ):
        make_trainer(cfg, tmp_path / "r")
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize(
    "overrides",
    [
        ("algo=wcsac",),  # the gradient rule never reads d_delay
        ("algo=sac_lag",),
        ("algo=wcsac", "algo.kappa_rule=pid"),  # kd = 0: no derivative term
        ("algo=wcsac", "algo.kappa_rule=pid", "algo.pid.d_delay=151"),
    ],
)
@pytest.mark.parametrize("total_frames", [200, 800])  # 0 updates (all random), 150 updates
def test_a_delay_longer_than_the_run_is_accepted_without_a_derivative(overrides, total_frames):
    # a run too short for the default d_delay = 1 (0 updates: a smoke test) or for
    # 151, where the derivative term does not act, is valid: the refusal named an option
    # it does not read
    cfg = compose_config("env=tiny", *overrides, f"total_frames={total_frames}")
    validate_config(cfg)


def test_a_refused_command_leaves_no_run_directory(tmp_path):
    run = tmp_path / "run"
    result = subprocess.run(
        [
            sys.executable,
            "train.py",
            *TINY_CLI,
            "algo.kappa_rule=pid",
            "algo.pid.ki=-1",
            "total_frames=400",
            f"hydra.run.dir={run}",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 1
    assert result.stderr.strip().splitlines()[-1] == (
        "error: algo.pid.ki must be a finite number in [0, 1e+06], got -1"
    )
    assert "Traceback" not in result.stderr
    assert not run.exists()


@pytest.mark.slow
def test_pid_forward_compiles_with_fullgraph_and_steps_as_eager():
    import torch._inductor.config as inductor_config

    gains = PIDGains(kp=0.1, ki=0.01, kd=0.5, d_delay=2, p_ema=0.5, d_ema=0.5)
    eager = make_loss(risk_level=0.1, width=16, kappa_rule="pid", pid=gains)
    compiled_loss = make_loss(risk_level=0.1, width=16, kappa_rule="pid", pid=gains)
    compiled = torch.compile(compiled_loss, fullgraph=True)
    with inductor_config.patch(fallback_random=True):
        for seed in range(3):
            batch = make_batch(seed=seed)
            torch.manual_seed(seed)
            got = compiled(batch.clone())
            torch.manual_seed(seed)
            expected = eager(batch.clone())
            assert float(got["kappa"]) == pytest.approx(float(expected["kappa"]), rel=1e-4)
    for key, value in eager.constraint.state_dict().items():
        got = compiled_loss.constraint.state_dict()[key]
        assert torch.allclose(got.double(), value.double(), rtol=1e-4, atol=1e-6), key
