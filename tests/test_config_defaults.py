"""The paper presets are PAPER_OPTIONS; the presets (``preset=kit``, ``kit_2026_11``) set
what they say; saved runs and the κ advice compose as they ran.

(The config's defaults and the loss's are one definition, SafetyOptions, which
``preset=kit`` then changes for the trainer: test_options.py and below.)"""

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
    ("variant", "name"), [("wcsac_paper", "wcsac"), ("sac_lag_paper", "sac_lag")]
)
def test_paper_presets_are_the_paper_options_and_nothing_else(variant, name):
    """Beside the row as it was before the training-safety change (``preset=kit_2026_11``,
    whose StaticEnv κ advice is the authors'), the paper variant differs in PAPER_OPTIONS
    and its label only; under the default ``preset=kit`` it is the same paper variant
    (the episode window it keeps is read only by kappa_signal max/episodes)."""
    paper, base = (
        _algo(f"algo={variant}", "preset=kit_2026_11"),
        _algo(f"algo={name}", "preset=kit_2026_11"),
    )
    assert paper.name == name
    for key, value in PAPER_OPTIONS.items():
        assert paper[key] == value, key
    assert (paper.safety_critic, paper.alpha_init, paper.actor_lr) == ("gaussian", 1.0, None)
    different = {k for k in base if base[k] != paper[k]}
    assert different == {"label", *(k for k in PAPER_OPTIONS if base[k] != PAPER_OPTIONS[k])}
    under_kit = _algo(f"algo={variant}")
    assert under_kit.kappa_signal == "critic"
    assert {k for k in paper if paper[k] != under_kit[k]} == {"kappa_episode_window"}


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


ENVS = ["static", "tiny", "dynamic", "point_goal1", "point_goal2", "gymnasium"]


@pytest.mark.parametrize("env", ENVS)
def test_kappa_advice_is_the_authors_in_the_units_of_each_formulation(env):
    """The authors' κ advice (lr × 50, damping 10 on harder layouts) was made for a Γ
    held under d's per-step equivalent (1.5 at d = 15); the kit's formulation holds the
    episode cost at d, ten times larger: under ``preset=kit_2026_11`` its lr scale is
    theirs / 10 and its damping theirs / 100 (the damping weighs a 10× gap against a
    10× critic). The paper presets keep the authors' numbers under either preset;
    StaticEnv's advice (lr × 1, no damping) is the same in both, as is your own env's.
    The default ``preset=kit`` has one κ rate for every layout: 0.3 × lr, no damping."""
    harder = env not in ("static", "tiny", "gymnasium")
    for preset in ("kit", "kit_2026_11"):
        for variant in ("wcsac_paper", "sac_lag_paper"):
            paper = _algo(f"algo={variant}", f"env={env}", f"preset={preset}")
            advice = (50.0, 10.0) if harder else (1.0, 0.0)
            assert (paper.kappa_lr_scale, paper.damp_scale) == advice
    # d's per-step equivalent over d: 0.09999568 for the paper's d, γ and T (1 − γ^1000)
    ratio = per_step_cost_threshold(15.0, 0.99, 1000) / 15.0
    assert ratio == pytest.approx(0.1, abs=1e-5)
    for name in ("wcsac", "sac_lag"):
        before = _algo(f"algo={name}", f"env={env}", "preset=kit_2026_11")
        expected = (50.0 * 0.1, 10.0 * 0.1**2) if harder else (1.0, 0.0)
        assert (before.kappa_lr_scale, before.damp_scale) == pytest.approx(expected, rel=1e-12)
        kit = _algo(f"algo={name}", f"env={env}")
        assert (kit.kappa_lr_scale, kit.damp_scale) == (0.3, 0.0)


# What results/training_safety/ measured as C36 (StaticEnv) and D23 (DynamicEnv, also
# algo.damp_scale=0), on top of the defaults before the change; on DynamicEnv the PID
# rule from κ = 0.1, never under it, with no integral term, 50-step cost targets and
# SAC's actor rate (Y9, results/training_safety_dynamic/) in place of D23's gradient rule.
DYNAMIC_RULE = [
    "algo.kappa_rule=pid",
    "algo.kappa_min=0.1",
    "algo.kappa_init=0.1",
    "algo.pid.ki=0",
    "algo.cost_n_steps=50",
    "algo.actor_lr=1e-3",
]
# SAC-Lag's own values on DynamicEnv (S4, results/training_safety_dynamic/), after
# DYNAMIC_RULE (conf/algo/kappa_advice/per_algo/kit_sac_lag_dynamic.yaml)
DYNAMIC_SAC_LAG = [
    "algo.safety_critic=iqn",
    "algo.kappa_min=0.02",
    "algo.kappa_init=0.02",
    "algo.pid.max_kappa=0.3",
]
# SAC-Lag's own value on StaticEnv (L19, results/training_safety/, sixteenth round;
# conf/algo/kappa_advice/per_algo/kit_sac_lag_static.yaml)
STATIC_SAC_LAG = ["algo.safety_critic=iqn"]
SAC_LAG_OWN = {"dynamic": DYNAMIC_SAC_LAG, "static": STATIC_SAC_LAG}
# What a SAC-Lag DynamicEnv run had under preset=kit before S4 (its mean critic, κ ≥ 0.1,
# the PID's default bound); a run begun then resumes only with these
SAC_LAG_BEFORE_S4 = [
    "algo.safety_critic=gaussian",
    "algo.kappa_min=0.1",
    "algo.pid.max_kappa=100.0",
]
# DynamicEnv's κ rule under preset=kit from D21 (results/training_safety/, eleventh
# round) until Y9: the PID rule at its own gains, κ >= 0.1 from log 2, 10-step targets.
DYNAMIC_D21 = [
    "algo.kappa_init=0.6931471805599453",
    "algo.pid.ki=1e-06",
    "algo.cost_n_steps=10",
    "algo.actor_lr=0.0003",
]
TRAINING_SAFETY_OPTIONS = [
    "algo.safety_critic=iqn",
    "algo.kappa_signal=max",
    "algo.kappa_episode_statistic=cvar",
    "algo.kappa_episode_window=10",
    "algo.kappa_lr_scale=0.3",
    "algo.alpha_init=0.1",
    "algo.actor_lr=3e-4",
    "algo.damp_scale=0",
]


def _whole(*overrides: str) -> dict:
    from omegaconf import OmegaConf

    from wcsac_rl.training.checkpoint import _leaves

    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("config", overrides=list(overrides))
    return _leaves(OmegaConf.to_container(cfg, resolve=True))


@pytest.mark.parametrize("env", ENVS)
@pytest.mark.parametrize("algo", ["wcsac", "sac_lag"])
def test_the_kit_preset_is_the_measured_candidate_on_the_defaults_before_it(algo, env):
    """``preset=kit`` (the default) is exactly the earlier defaults with the options the
    training-safety study screened (C36; Y9 on DynamicEnv), and nothing else, in every
    key of the run's config, for WCSAC and SAC-Lag on every layout (SAC-Lag keeps its
    mean critic except where it has its own values: S4 on DynamicEnv, L19 on
    StaticEnv)."""
    options = [
        o
        for o in TRAINING_SAFETY_OPTIONS
        if not (algo == "sac_lag" and o == "algo.safety_critic=iqn")
    ]
    if env == "dynamic":
        options += DYNAMIC_RULE
    if algo == "sac_lag":
        options += SAC_LAG_OWN.get(env, [])
    before = _whole(f"algo={algo}", f"env={env}", "preset=kit_2026_11", *options)
    assert _whole(f"algo={algo}", f"env={env}") == before
    assert _whole(f"algo={algo}", f"env={env}", "preset=kit") == before


@pytest.mark.parametrize("algo", ["sac", "cpo", "random"])
def test_the_preset_leaves_the_algorithms_without_a_lagrangian_alone(algo):
    """SAC, CPO and the random policy take nothing from either preset (no safety keys,
    SAC's own entropy weight and learning rates)."""
    kit = _whole(f"algo={algo}")
    assert _whole(f"algo={algo}", "preset=kit_2026_11") == kit
    assert not any(k.startswith(("algo.kappa", "algo.safety")) for k in kit)
    if algo == "sac":
        assert (kit["algo.alpha_init"], kit["algo.actor_lr"]) == (1.0, None)


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
    "ensemble_reading": "max",
    "k_ucb": 0.5,
    "prior_scale": 0.0,
    "k_ucb_lr": 0.0,
    "k_ucb_max": 2.0,
    "damp_clamp": False,
    "kappa_signal_every": 1,
    "shield.candidates": 0,
    "shield.scale": 1.0,
}


# committed studies: their experiment (results/dynamic_laptop/ ran before the κ advice
# moved to the kit's units: its RESULTS.md says so; dynamic_kappa_units is it since)
COMMITTED_TABLE1 = {
    "static_laptop": "table1_static_laptop",
    "dynamic_kappa_units": "table1_dynamic_laptop",
}


@pytest.mark.parametrize(
    ("study", "run"),
    sorted(
        (study, p.name)
        for study in COMMITTED_TABLE1
        for p in (CONF.parent / "results" / study / "runs").iterdir()
        if p.name.startswith(("wcsac", "sac"))
    ),
)
def test_the_committed_table1_rows_are_what_their_experiment_composes(study, run):
    """Every committed Table 1 row (StaticEnv; DynamicEnv with the κ advice in the kit's
    units) is what its experiment file composes today (it selects
    ``preset=kit_2026_11``): the sweep runs again as committed."""
    import yaml
    from omegaconf import OmegaConf

    from wcsac_rl.training.checkpoint import _leaves

    saved = yaml.safe_load(
        (CONF.parent / "results" / study / "runs" / run / "config.yaml").read_text()
    )
    row = run.removesuffix(f"_{saved['env']['name']}_seed{saved['seed']}")
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose(
            "config",
            overrides=[
                f"experiment={COMMITTED_TABLE1[study]}",
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


def test_the_keys_a_resume_names_as_the_presets_are_the_keys_they_differ_in():
    """checkpoint.PRESET_KEYS (what a refused resume blames on the preset) is every key in
    which the two presets differ, for WCSAC and SAC-Lag on every layout."""
    from wcsac_rl.training.checkpoint import PRESET_KEYS

    differing = set()
    for algo in ("wcsac", "sac_lag"):
        for env in ENVS:
            kit, before = (
                _whole(f"algo={algo}", f"env={env}"),
                _whole(f"algo={algo}", f"env={env}", "preset=kit_2026_11"),
            )
            differing |= {k for k in kit if kit[k] != before[k]}
    assert differing == PRESET_KEYS


PRESET_HINT = (
    "(a run begun before the config's default preset changed continues with "
    "preset=kit_2026_11 on the command line)"
)


@pytest.mark.parametrize(
    ("base", "then", "hint"),
    [
        (("algo=wcsac", "env=tiny"), ("preset=kit_2026_11",), PRESET_HINT),
        (("algo=sac_lag", "env=tiny"), ("preset=kit_2026_11",), PRESET_HINT),
        (
            ("algo=wcsac", "env=dynamic", "risk_level=0.5"),
            ("algo.kappa_rule=gradient", "algo.kappa_min=0", *DYNAMIC_D21),
            None,
        ),
        (("algo=wcsac", "env=dynamic", "risk_level=0.5"), tuple(DYNAMIC_D21), None),
        (("algo=sac_lag", "env=dynamic"), (*SAC_LAG_BEFORE_S4, *DYNAMIC_D21), None),
        (("algo=sac_lag", "env=dynamic"), (*SAC_LAG_BEFORE_S4, "algo.kappa_init=0.1"), None),
        (("algo=sac_lag", "env=static"), ("algo.safety_critic=gaussian",), None),
    ],
    ids=[
        "wcsac-kit_2026_11",
        "sac_lag-kit_2026_11",
        "dynamic-kit-gradient-rule",
        "dynamic-kit-d21",
        "sac_lag-dynamic-kit-d21",
        "sac_lag-dynamic-kit-y9",
        "sac_lag-static-kit-mean-critic",
    ],
)
def test_a_run_begun_under_an_earlier_default_resumes_only_as_it_began(tmp_path, base, then, hint):
    """``resume=auto`` on a run made under an earlier default: one made under
    ``preset=kit_2026_11``, DynamicEnv ones made under ``preset=kit`` while its κ rule was
    the gradient rule (as the card's command ran before) or D21's PID rule, and a
    StaticEnv SAC-Lag one made while ``preset=kit`` gave it its mean critic.
    Under today's default it is refused in one line that ends with what to add (nothing
    of the run is touched); with exactly that added it continues, in every key of its
    config as it began (the actor's rate too, which a resume may change)."""
    import re

    from _training_helpers import compose_config
    from omegaconf import OmegaConf

    from wcsac_rl.training import ConfigError, make_trainer
    from wcsac_rl.training.checkpoint import _leaves, load_checkpoint

    run_dir = tmp_path / "run"
    base = (*base, "resume=auto")
    first = make_trainer(compose_config(*base, *then, "total_frames=400"), run_dir)
    try:
        first.run()
    finally:
        first.close()
    files = {p: p.read_bytes() for p in run_dir.rglob("*") if p.is_file() and p.name != ".lock"}
    with pytest.raises(ConfigError) as err:
        make_trainer(compose_config(*base), run_dir).close()
    message = str(err.value)
    assert "\n" not in message
    if hint is not None:
        assert message.endswith(hint)
        added = then
    else:
        found = re.search(
            r" \(a (?:DynamicEnv|StaticEnv) run begun under an earlier preset=kit default "
            r"continues with (.+) on the command line\)$",
            message,
        )
        assert found is not None, message
        added = tuple(found.group(1).split(" "))
        assert sorted(o.split("=")[0] for o in added) == sorted(o.split("=")[0] for o in then)
    assert {p: p.read_bytes() for p in files} == files
    began = _leaves(load_checkpoint(run_dir / "checkpoints" / "last.pt")["config"])
    resumed = make_trainer(compose_config(*base, *added), run_dir)
    try:
        resumed.run()
    finally:
        resumed.close()
    now = _leaves(OmegaConf.to_container(resumed.cfg, resolve=True))
    changed = {k for k in began if k in now and began[k] != now[k]}
    assert changed <= {"resume", "total_frames"}, changed
    rows = (run_dir / "progress.csv").read_text().splitlines()
    assert len(rows) == 1 + 2  # header, the first session's epoch and the resumed one's


def test_the_dynamic_rule_hint_is_not_offered_for_a_key_the_run_never_had():
    """A DynamicEnv run whose config predates a refused κ option (no value for it) gets
    the general preset hint, not the DynamicEnv one, which would list nothing for that
    key: no value of it would continue the run."""
    from _training_helpers import compose_config
    from omegaconf import OmegaConf

    from wcsac_rl.training.checkpoint import PRESET_HINT as GENERAL_HINT
    from wcsac_rl.training.checkpoint import _preset_hint

    cfg = compose_config("algo=wcsac", "env=dynamic", "risk_level=0.5")
    saved = OmegaConf.to_container(cfg, resolve=True)
    del saved["algo"]["kappa_rule"]
    assert _preset_hint(["algo.kappa_rule"], saved, cfg) == GENERAL_HINT
    saved["algo"]["kappa_rule"] = "gradient"
    hint = _preset_hint(["algo.kappa_rule"], saved, cfg)
    assert hint.endswith(
        " (a DynamicEnv run begun under an earlier preset=kit default "
        "continues with algo.kappa_rule=gradient on the command line)"
    )
