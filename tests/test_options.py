"""Every WCSAC / SAC-Lag option has one definition: a field of ``SafetyOptions``
(``wcsac_rl/options.py``). The loss's keyword defaults are its fields, the composed
config starts from it (Hydra's ConfigStore), the YAML files set only what differs, and a
bad value of any field is one line naming ``algo.<field>`` (the loss: ``<field>``), checked
by the same function; a misspelt option names the closest one."""

from __future__ import annotations

import dataclasses
import inspect
import math
import re
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from _loss_helpers import make_loss
from _training_helpers import CONF, ROOT, compose_config
from hydra import compose, initialize_config_dir

from wcsac_rl import WCSACLoss, config_schema
from wcsac_rl.objectives import EpisodeCostWindow, NStepCost
from wcsac_rl.objectives.constraint import HeldStatistic
from wcsac_rl.objectives.ensemble_head import AdaptivePessimism
from wcsac_rl.objectives.safety_head import CostTarget
from wcsac_rl.options import (
    LOSS_OPTIONS,
    PAPER_OPTIONS,
    IQNOptions,
    PIDGains,
    SafetyOptions,
    ShieldOptions,
    check_value,
    config_defaults,
    option,
    option_spec,
    read_options,
)
from wcsac_rl.training import ConfigError, validate_config
from wcsac_rl.training.config_keys import check_override_keys

GROUPS = {"iqn": IQNOptions, "pid": PIDGains, "shield": ShieldOptions}


def _leaves() -> list[tuple[str, type, str]]:
    """``(config key below algo, its dataclass, its field)`` for every option."""
    out = []
    for f in dataclasses.fields(SafetyOptions):
        if f.name in GROUPS:
            out += [
                (f"{f.name}.{g.name}", GROUPS[f.name], g.name)
                for g in dataclasses.fields(GROUPS[f.name])
            ]
        else:
            out.append((f.name, SafetyOptions, f.name))
    return out


LEAVES = _leaves()
BAD = {"choice": "nope", "flag": "maybe", "number": "abc", "integer": -1, "risk_level": 0}


# ------------------------------------------------------------------ the loss
def test_the_parts_options_are_the_fields():
    """Each field of ``SafetyHeadOptions`` and ``SignalOptions`` is the ``SafetyOptions``
    (or ``IQNOptions``) field of that name: its default and its very metadata, no second
    definition; every option the loss reads belongs to one part."""
    from wcsac_rl.objectives.loss_options import PART_OF_OPTION, SafetyHeadOptions, SignalOptions

    for part in (SafetyHeadOptions, SignalOptions):
        for f in dataclasses.fields(part):
            cls = SafetyOptions if f.name in SafetyOptions.__dataclass_fields__ else IQNOptions
            source = cls.__dataclass_fields__[f.name]
            assert (f.default, f.metadata) == (source.default, source.metadata), f.name
            assert f.metadata["option"] is source.metadata["option"], f.name
    assert set(LOSS_OPTIONS) - {"risk_level"} <= set(PART_OF_OPTION)


def test_the_loss_defaults_are_the_papers_recipe():
    """``WCSACLoss``'s own keywords are at most SACLoss's count (22; SACLoss's own pass
    through ``**sac_kwargs`` and count as SACLoss's), and with none but the networks,
    α and d it is the paper's WCSAC for its critic's kind (``loss_parts(PAPER_OPTIONS)``),
    β from SACLoss's 1."""
    from wcsac_rl.objectives import PAPER_OPTIONS, loss_parts

    own = [
        p.name
        for p in inspect.signature(WCSACLoss.__init__).parameters.values()
        if p.kind is inspect.Parameter.KEYWORD_ONLY
    ]
    assert len(own) <= 22, own
    for kind in ("gaussian", "iqn"):
        paper = loss_parts({**PAPER_OPTIONS, "safety_critic": kind})
        networks = make_loss(kind=kind)
        built = WCSACLoss(
            networks.actor_network, [networks.qvalue_network] * 2, networks.safety_network
        )
        assert (built.head_options, built.signal_options) == (
            paper["safety_head"],
            paper["signal"],
        )
        assert type(built.constraint) is type(paper["constraint"])
        assert repr(built.constraint) == repr(paper["constraint"])
        assert float(built.kappa) == pytest.approx(float(paper["constraint"].kappa))
        assert float(built.log_alpha.exp()) == pytest.approx(1.0)


@pytest.mark.parametrize("name", LOSS_OPTIONS)
def test_the_loss_refuses_a_bad_value_of_each_option_by_name(name):
    """A bad value of an option is one ``ValueError`` line naming it, from the part's
    options (a recipe, as the config gives them: ``loss_parts``)."""
    cls = SafetyOptions if name in SafetyOptions.__dataclass_fields__ else IQNOptions
    spec = option_spec(cls, name)
    message = (
        "tail fraction" if spec.kind == "risk_level" else f"{name} must be {spec.requirement()}"
    )
    with pytest.raises(ValueError, match=re.escape(message)) as err:
        make_loss(**{name: BAD[spec.kind]})
    assert "\n" not in str(err.value)


@pytest.mark.parametrize(
    ("part", "name"),
    [
        ("SafetyHeadOptions", "variance_target"),
        ("SafetyHeadOptions", "num_quantiles"),
        ("SafetyHeadOptions", "cost_gamma"),
        ("SignalOptions", "kappa_signal_every"),
        ("SignalOptions", "kappa_states"),
    ],
)
def test_each_parts_options_refuse_a_bad_value_by_name(part, name):
    from wcsac_rl.objectives import loss_options

    cls = SafetyOptions if name in SafetyOptions.__dataclass_fields__ else IQNOptions
    spec = option_spec(cls, name)
    with pytest.raises(ValueError) as err:
        getattr(loss_options, part)(**{name: BAD[spec.kind]})
    assert str(err.value) == f"{name} must be {spec.requirement()}, got {BAD[spec.kind]!r}"


def test_a_misspelt_loss_keyword_names_the_closest_and_an_option_names_its_part():
    with pytest.raises(TypeError, match=re.escape("'alpha_int' (did you mean alpha_init?)")):
        make_loss(alpha_int=1.0)
    loss = make_loss()
    networks = (loss.actor_network, [loss.qvalue_network] * 2, loss.safety_network)
    with pytest.raises(TypeError) as err:
        WCSACLoss(*networks, kappa_init=1.0)
    assert str(err.value) == (
        "'kappa_init' is an option of a part of the loss: give "
        "constraint=GradientLagrangian(kappa_init=...)"
    )
    with pytest.raises(TypeError, match=re.escape("(did you mean cost_n_steps? give safety_head")):
        WCSACLoss(*networks, cost_n_step=1)
    with pytest.raises(ValueError, match=r"^signal must be a SignalOptions, got dict$"):
        WCSACLoss(*networks, signal={"kappa_states": "replay"})


# ------------------------------------------------------------------ the config
def _recipe(path: Path) -> dict:
    """A recipe file's own values (its defaults list and the files' name left out)."""
    node = yaml.safe_load(path.read_text()) or {}
    return {k: v for k, v in node.items() if k not in ("defaults", "recipe")}


def test_the_composed_config_starts_from_the_dataclass():
    """The dataclass's defaults, then what the algorithm's recipe sets (conf/algo/wcsac.yaml;
    test_config_defaults.py pins it to the measured candidate)."""
    defaults = config_defaults(SafetyOptions)
    recipe = _recipe(CONF / "algo" / "wcsac.yaml")
    algo = compose_config("algo=wcsac", small=False).algo
    for key, value in defaults.items():
        if key != "risk_level":  # (the run's α: ${risk_level})
            assert algo[key] == recipe.get(key, value), key
    assert set(recipe) - set(defaults) == {"name", "label", "alpha_init", "actor_lr"}


def test_changing_a_default_changes_the_composed_config_and_the_loss_it_builds(monkeypatch):
    """The schema Hydra composes is the dataclass: a subclass with another default,
    registered in its place, gives configs (and so losses) with that default."""
    from wcsac_rl.envs import make_env
    from wcsac_rl.training import builders

    @dataclasses.dataclass(frozen=True)
    class Changed(SafetyOptions):
        kappa_init: float = option(1.5, "another default", "number", low=0.0, low_open=True)
        kappa_signal_every: int = option(3, "another default", "integer", low=1)

    monkeypatch.setattr(config_schema, "SafetyOptions", Changed)
    config_schema.register_configs()
    try:
        cfg = compose_config("algo=wcsac", "env=tiny")
        assert (cfg.algo.kappa_init, cfg.algo.kappa_signal_every) == (1.5, 3)
        env = make_env("tiny", seed=0)
        try:
            loss = builders.make_loss(cfg, builders.make_agent(cfg, env), 100)
        finally:
            env.close()
        assert float(loss.kappa) == pytest.approx(1.5) and loss.kappa_signal_every == 3
    finally:
        monkeypatch.undo()
        config_schema.register_configs()
    assert compose_config("algo=wcsac").algo.kappa_init == SafetyOptions.kappa_init


@pytest.mark.parametrize(("key", "cls", "name"), LEAVES, ids=[k for k, _, _ in LEAVES])
def test_a_bad_value_of_every_field_is_one_line_naming_it(key, cls, name):
    spec = option_spec(cls, name)
    bad = BAD[spec.kind]
    with pytest.raises(ConfigError) as err:
        validate_config(compose_config("env=tiny", f"algo.{key}={bad}"))
    message = str(err.value)
    assert "\n" not in message
    if spec.kind == "risk_level":
        assert message.startswith(f"algo.{key} α must be a number in (0, 1], got {bad!r}")
    else:
        assert message == f"algo.{key} must be {spec.requirement()}, got {bad!r}"


@pytest.mark.parametrize(
    ("override", "message"),
    [
        (
            "algo.kappa_inti=0.5",
            "unknown config key algo.kappa_inti (did you mean algo.kappa_init?)",
        ),
        ("algo.iqn.num_quantile=5", "(did you mean algo.iqn.num_quantiles?)"),
        ("algo.pid.kq=1", "(did you mean algo.pid.kp?)"),
        ("algo.shield.scael=1", "(did you mean algo.shield.scale?)"),
    ],
)
def test_a_misspelt_option_on_the_command_line_names_the_closest(override, message):
    with pytest.raises(ConfigError, match=re.escape(message)):
        check_override_keys(["algo=wcsac", override])


def test_an_added_misspelt_option_names_the_closest_once_composed():
    with pytest.raises(ConfigError, match=re.escape("(did you mean algo.kappa_init?)")):
        validate_config(compose_config("env=tiny", "+algo.kappa_inti=0.5"))
    with pytest.raises(
        ConfigError, match=re.escape("unknown PID option algo.pid.kq (did you mean algo.pid.kp?)")
    ):
        validate_config(compose_config("env=tiny", "+algo.pid.kq=1"))


def test_the_yaml_files_set_only_what_differs_from_the_schema():
    """Each recipe file sets only what differs from what it starts from (the schema and
    off_policy.yaml; the paper variants: PAPER_OPTIONS too, which they never repeat), and
    each layout file only what differs from its algorithm's file."""
    from wcsac_rl.recipes import layout_files

    defaults = config_defaults(SafetyOptions)
    off_policy = yaml.safe_load((CONF / "algo" / "off_policy.yaml").read_text())
    for name in ("wcsac", "sac_lag", "wcsac_paper", "sac_lag_paper"):  # (the schema's users)
        paper = name.endswith("_paper")
        inherited = {**off_policy, **defaults, **(PAPER_OPTIONS if paper else {})}
        recipe = _recipe(CONF / "algo" / f"{name}.yaml")
        for key, value in recipe.items():
            if key in inherited:
                assert value != inherited[key], f"{name}.yaml: {key} repeats what it inherits"
            if paper:
                assert key not in PAPER_OPTIONS, f"{name}.yaml: {key} is PAPER_OPTIONS'"
    for (name, _env), path in layout_files(CONF).items():
        paper = name.endswith("_paper")
        base = {
            **off_policy,
            **defaults,
            **(PAPER_OPTIONS if paper else {}),
            **_recipe(CONF / "algo" / f"{name}.yaml"),
        }
        for key, value in _recipe(path).items():
            if isinstance(value, dict):  # (pid: each gain against the default's)
                for sub, v in value.items():
                    assert v != base[key][sub], f"{path.name}: {key}.{sub} repeats"
            else:
                assert value != base[key], f"{path.name}: {key} repeats"


@pytest.mark.parametrize("key", ["cost_bootstrap_truncated", "kappa_signal", "shield"])
def test_an_option_a_config_lacks_is_refused_naming_it(key):
    """Nothing fills in an option a config lacks (a stored run's config of another
    commit's kit is refused before this: tests/test_config_defaults.py)."""
    values = config_defaults(SafetyOptions)
    assert read_options(SafetyOptions, values, prefix="algo.") == SafetyOptions()
    del values[key]
    line = f"algo.{key} is missing (a composed config has every option)"
    with pytest.raises(ValueError, match=f"^{re.escape(line)}$"):
        read_options(SafetyOptions, values, prefix="algo.")


def test_the_paper_options_are_a_valid_replacement_of_the_fields():
    paper = dataclasses.replace(SafetyOptions(), **PAPER_OPTIONS)
    assert all(getattr(paper, k) == v for k, v in PAPER_OPTIONS.items())
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        algo = compose("config", overrides=["algo=wcsac_paper"]).algo
    assert all(algo[k] == v for k, v in PAPER_OPTIONS.items())


def test_the_options_load_without_torch():
    """``wcsac-train --help`` composes the config: the schema must not need torch."""
    import subprocess
    import sys

    code = "import sys, wcsac_rl.config_schema; print('torch' in sys.modules)"
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True
    )
    assert out.stdout.strip() == "False"


def test_nested_options_refuse_a_bad_gain_by_name():
    with pytest.raises(ValueError, match=re.escape("pid.kp must be a finite number in [0, 1e+06]")):
        PIDGains(kp=-1.0)
    with pytest.raises(ValueError, match=re.escape("iqn.num_cosines must be an integer >= 1")):
        IQNOptions(num_cosines=0)
    with pytest.raises(
        ValueError, match=re.escape("shield.scale must be in (0, 1e+06] (a number)")
    ):
        ShieldOptions(scale=0.0)
    assert Path(inspect.getfile(SafetyOptions)).name == "options.py"


@pytest.mark.parametrize("rule", ["gradient", "pid"])
def test_a_kappa_floor_above_the_start_is_refused_alike(tmp_path, rule):
    """kappa_min beside kappa_init: the constraint and the config validator refuse a
    floor above where κ starts in the same words."""
    from wcsac_rl.objectives.constraint import make_constraint
    from wcsac_rl.training import make_trainer

    with pytest.raises(ValueError) as loss_error:
        make_constraint(rule, kappa_init=0.2, kappa_min=0.5)
    words = str(loss_error.value)
    assert words == "kappa_min must be <= kappa_init (0.2, where κ starts), got 0.5"
    expected = re.sub(r"\b(kappa_min|kappa_init)\b", r"algo.\1", words)
    overrides = [f"algo.kappa_rule={rule}", "algo.kappa_init=0.2", "algo.kappa_min=0.5"]
    with pytest.raises(ConfigError, match=re.escape(expected)):
        make_trainer(compose_config("env=tiny", *overrides), tmp_path / "r")
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize(
    ("rule", "kappa_init", "kappa_max"),
    [("gradient", 0.5, 0.1), ("pid", 0.05, 0.1)],
)
def test_the_kappa_bound_relations_are_defined_once(tmp_path, rule, kappa_init, kappa_max):
    """kappa_max beside kappa_init and kappa_rule: the constraint and the config validator
    refuse the same values in the same words, the config's naming ``algo.<key>``."""
    from wcsac_rl.objectives.constraint import make_constraint
    from wcsac_rl.training import make_trainer

    with pytest.raises(ValueError) as loss_error:
        make_constraint(rule, kappa_init=kappa_init, kappa_max=kappa_max)
    words = str(loss_error.value)
    expected = re.sub(r"\b(kappa_max|kappa_init|kappa_rule|pid\.max_kappa)\b", r"algo.\1", words)
    overrides = [
        f"algo.kappa_rule={rule}",
        f"algo.kappa_init={kappa_init}",
        f"algo.kappa_max={kappa_max}",
    ]
    with pytest.raises(ConfigError, match=re.escape(expected)):
        make_trainer(compose_config("env=tiny", *overrides), tmp_path / "r")
    assert not (tmp_path / "r").exists()


KEYS = WCSACLoss.default_keys()


@pytest.mark.parametrize(
    ("build", "override"),
    [
        (lambda: CostTarget(KEYS, gamma=1.5), "algo.cost_gamma=1.5"),
        (lambda: CostTarget(KEYS, n_steps=0), "algo.cost_n_steps=0"),
        (lambda: NStepCost(2.0, 0.99), "algo.cost_n_steps=2.0"),
        (lambda: EpisodeCostWindow(0.5, window=0), "algo.kappa_episode_window=0"),
        (lambda: EpisodeCostWindow(0.5, test_window=-1), "algo.kappa_test_window=-1"),
        (lambda: HeldStatistic(0), "algo.kappa_signal_every=0"),
        (lambda: AdaptivePessimism(math.nan, lr=0.1, k_max=1.0), "algo.k_ucb=nan"),
    ],
    ids=lambda case: case if isinstance(case, str) else "",
)
def test_a_part_and_the_config_refuse_a_value_by_the_same_rule(build, override):
    """A part built directly checks its argument against the option's spec: the same
    rule, in the same words after its argument's name, as the config's ``algo.<key>``."""
    with pytest.raises(ValueError) as built:
        build()
    with pytest.raises(ConfigError) as config:
        validate_config(compose_config("env=tiny", override))
    built, config = str(built.value), str(config.value)
    assert "\n" not in built and " must be " in built
    assert built.split(" must be ", 1)[1] in config, (built, config)
    assert f"{override.split('=')[0]} must be " in config


def test_an_integer_of_any_type_is_an_integer_and_a_float_is_not():
    for whole in (3, np.int64(3), np.int32(3), torch.tensor(3)):
        check_value("cost_n_steps", whole, "cost_n_steps")
        assert NStepCost(whole, np.float32(0.99)).n_steps == 3
    for bad in (3.0, np.float64(3.0), True, "3", torch.tensor(3.0)):
        with pytest.raises(ValueError, match="cost_n_steps must be an integer >= 1, got"):
            check_value("cost_n_steps", bad, "cost_n_steps")
