"""The paper presets are PAPER_OPTIONS; saved runs and the κ advice compose as they ran.

(The config's defaults and the loss's are one definition, SafetyOptions: test_options.py.)"""

from __future__ import annotations

from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from wcsac_rl.objectives import PAPER_OPTIONS, per_step_cost_threshold

CONF = Path(__file__).resolve().parents[1] / "conf"


def _algo(*overrides: str):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose("config", overrides=list(overrides)).algo


@pytest.mark.parametrize(
    ("preset", "name"), [("wcsac_paper", "wcsac"), ("sac_lag_paper", "sac_lag")]
)
def test_paper_presets_are_the_paper_options_and_nothing_else(preset, name):
    paper, base = _algo(f"algo={preset}"), _algo(f"algo={name}")
    assert paper.name == name
    for key, value in PAPER_OPTIONS.items():
        assert paper[key] == value, key
    different = {k for k in base if base[k] != paper[k]}
    assert different == {"label", *(k for k in PAPER_OPTIONS if base[k] != PAPER_OPTIONS[k])}


def test_paper_preset_builds_the_papers_loss():
    from wcsac_rl.envs import make_env
    from wcsac_rl.training import builders

    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("config", overrides=["algo=wcsac_paper", "env=tiny", "risk_level=0.1"])
    env = make_env("tiny", seed=0)
    try:
        loss = builders.make_loss(cfg, builders.make_agent(cfg, env), 100)
    finally:
        env.close()
    assert loss.kappa_states == "replay" and loss.cost_n_steps == 1
    assert loss.cost_gamma == pytest.approx(float(cfg.algo.gamma))
    # the per-step threshold of a discounted critic, not d itself
    expected = cfg.cost_limit * (1 - cfg.algo.gamma**100) / ((1 - cfg.algo.gamma) * 100)
    assert float(loss.cost_threshold) == pytest.approx(expected, rel=1e-6)
    assert builders.make_postproc(loss) is None


def test_saved_configs_without_the_truncation_option_keep_bootstrapping():
    """A run saved before ``cost_bootstrap_truncated`` existed bootstrapped its safety
    critic across time limits: resuming it keeps that; a current config (the key at
    null, γ_c = 1) stops there."""
    from omegaconf import open_dict

    from wcsac_rl.envs import make_env
    from wcsac_rl.training import builders

    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("config", overrides=["algo=wcsac", "env=tiny", "risk_level=0.1"])
    env = make_env("tiny", seed=0)
    try:
        current = builders.make_loss(cfg, builders.make_agent(cfg, env), 100)
        with open_dict(cfg):
            del cfg.algo["cost_bootstrap_truncated"]
        saved = builders.make_loss(cfg, builders.make_agent(cfg, env), 100)
    finally:
        env.close()
    assert current.cost_gamma == 1.0 and current.cost_bootstrap_truncated is False
    assert saved.cost_bootstrap_truncated is True


def test_a_config_saved_before_the_safety_options_validates_and_builds_what_it_ran():
    """A run saved before the safety critic's and κ's options existed (resumed with
    ``resume=<run dir>``, which keeps the run's own config) passes validation, and its
    loss gets what such a run did: the paper's choices (``SAVED_RUN_VALUES``)."""
    from omegaconf import open_dict

    from wcsac_rl.envs import make_env
    from wcsac_rl.options import SAVED_RUN_VALUES
    from wcsac_rl.training import builders, validate_config

    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("config", overrides=["algo=wcsac", "env=tiny", "risk_level=0.1"])
    with open_dict(cfg):
        for key in {*SAVED_RUN_VALUES, "kappa_episode_window"}:
            del cfg.algo[key]
    validate_config(cfg)
    env = make_env("tiny", seed=0)
    try:
        loss = builders.make_loss(cfg, builders.make_agent(cfg, env), 100)
    finally:
        env.close()
    assert (loss.variance_target_kind, loss.kappa_states, loss.kappa_statistic) == (
        "moment",
        "replay",
        "mean",
    )
    assert (loss.kappa_signal, loss.cost_n_steps, loss.nonnegative_cost) == ("critic", 1, False)
    assert loss.cost_gamma == 0.99 and loss.cost_bootstrap_truncated is True
    assert loss.safety_critic_kind == "gaussian"


@pytest.mark.parametrize("env", ["static", "tiny", "dynamic", "point_goal1", "point_goal2"])
def test_kappa_advice_is_the_authors_in_the_units_of_each_formulation(env):
    """The authors' κ advice (lr × 50, damping 10 on harder layouts) was made for a Γ
    held under d's per-step equivalent (1.5 at d = 15); the kit's formulation holds the
    episode cost at d, ten times larger: its lr scale is theirs / 10 and its damping
    theirs / 100 (the damping weighs a 10× gap against a 10× critic). The paper presets
    keep the authors' numbers; StaticEnv's advice (lr × 1, no damping) is the same in both."""
    harder = env not in ("static", "tiny")
    for preset in ("wcsac_paper", "sac_lag_paper"):
        paper = _algo(f"algo={preset}", f"env={env}")
        assert (paper.kappa_lr_scale, paper.damp_scale) == ((50.0, 10.0) if harder else (1.0, 0.0))
    # d's per-step equivalent over d: 0.09999568 for the paper's d, γ and T (1 − γ^1000)
    ratio = per_step_cost_threshold(15.0, 0.99, 1000) / 15.0
    assert ratio == pytest.approx(0.1, abs=1e-5)
    for name in ("wcsac", "sac_lag"):
        kit = _algo(f"algo={name}", f"env={env}")
        expected = (50.0 * 0.1, 10.0 * 0.1**2) if harder else (1.0, 0.0)
        assert (kit.kappa_lr_scale, kit.damp_scale) == pytest.approx(expected, rel=1e-12)


# options added since those runs, and their value then (absent from their config)
ADDED_SINCE = {
    "kappa_rule": "gradient",
    "kappa_episode_statistic": "cvar",
    "actor_lr": None,
    "kappa_max": None,
    "kappa_test_window": 0,
    "kappa_min": 0.0,
    "num_safety_nets": 1,
    "ensemble_target": "own",
}


@pytest.mark.parametrize(
    "run",
    sorted(
        p.name
        for p in (CONF.parent / "results" / "static_laptop" / "runs").iterdir()
        if p.name.startswith(("wcsac", "sac_lag"))
    ),
)
def test_the_committed_static_rows_are_reachable_with_the_paper_rule(run):
    import yaml
    from omegaconf import OmegaConf

    from wcsac_rl.training.checkpoint import _leaves

    saved = yaml.safe_load(
        (CONF.parent / "results" / "static_laptop" / "runs" / run / "config.yaml").read_text()
    )
    row = run.removesuffix(f"_static_seed{saved['seed']}")
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose(
            "config",
            overrides=[
                "env=static",
                f"+row={row}",
                f"seed={saved['seed']}",
            ],
        )
    now = _leaves(OmegaConf.to_container(cfg.algo, resolve=True))
    then = _leaves(saved["algo"])
    assert {k: v for k, v in now.items() if k in then} == then
    for key in set(now) - set(then):
        if not key.startswith("pid."):  # (the PID gains do nothing under the gradient rule)
            assert now[key] == ADDED_SINCE[key], key
