"""The named recipes (``wcsac_rl.recipes``: ``KIT_OPTIONS``, ``kit_options(layout)``,
``recipe_options(algorithm, layout)``, with ``PAPER_OPTIONS``) are what ``train.py``
composes, key by key, for every algorithm with a safety critic on every layout; the
loss the trainer builds from a composed config is the loss a user's own loop builds
from the named recipe; and ``WCSACLoss`` with no option is the paper's (``algo=wcsac_paper``)."""

from __future__ import annotations

import math
import shutil
from collections.abc import Mapping
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from wcsac_rl import WCSACLoss
from wcsac_rl.objectives import (
    KIT_OPTIONS,
    PAPER_OPTIONS,
    kit_options,
    loss_parts,
    recipe_options,
)
from wcsac_rl.options import SafetyOptions, config_defaults
from wcsac_rl.recipes import LAYOUTS, RECIPE_ALGORITHMS, TRAINER_KEYS, _compose, _safety_algorithms

CONF = Path(__file__).resolve().parents[1] / "conf"
NOT_RECIPE = {"name", "label", "recipe"}  # (what the node is called, not what it sets)


def _flat(node: dict, prefix: str = "") -> dict:
    out = {}
    for key, value in node.items():
        if isinstance(value, Mapping):
            out |= _flat(value, f"{prefix}{key}.")
        else:
            out[f"{prefix}{key}"] = value
    return out


def _composed(algorithm: str, layout: str):
    overrides = [f"algo={algorithm}", f"env={layout}", "risk_level=0.1"]
    if layout == "gymnasium":
        overrides.append("env.id=MyTask-v0")
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose("config", overrides=overrides)


def _base() -> dict:
    off_policy = OmegaConf.to_container(OmegaConf.load(CONF / "algo" / "off_policy.yaml"))
    return _flat({**off_policy, **config_defaults(SafetyOptions)})


def _conf_copy(tmp_path: Path) -> Path:
    conf = tmp_path / "conf"
    shutil.copytree(CONF, conf)
    return conf


def test_a_recipe_is_read_from_its_yaml_files_only(tmp_path):
    """Editing ``conf/algo/wcsac.yaml`` (or its layout file) is the whole of changing the
    recipe: the named recipe is read from the files, not kept beside them."""
    conf = _conf_copy(tmp_path)
    path = conf / "algo" / "wcsac.yaml"
    path.write_text(path.read_text().replace("kappa_lr_scale: 0.3", "kappa_lr_scale: 0.7"))
    layout = conf / "algo" / "layout" / "wcsac_dynamic.yaml"
    layout.write_text(layout.read_text().replace("cost_n_steps: 50", "cost_n_steps: 20"))
    assert _compose(conf, "wcsac", "static")["kappa_lr_scale"] == 0.7
    assert _compose(conf, "wcsac", "dynamic")["cost_n_steps"] == 20
    assert _compose(CONF, "wcsac", "static")["kappa_lr_scale"] == 0.3
    assert RECIPE_ALGORITHMS == _safety_algorithms(conf)


def test_a_defaults_entry_the_reader_does_not_know_is_refused_naming_the_file(tmp_path):
    conf = _conf_copy(tmp_path)
    path = conf / "algo" / "wcsac.yaml"
    path.write_text(path.read_text().replace("  - _self_\n", "  - sac_lag\n  - _self_\n", 1))
    with pytest.raises(ValueError) as err:
        _compose(conf, "wcsac", "static")
    assert str(err.value).startswith(
        "conf/algo/wcsac.yaml: the defaults entry 'sac_lag' is not one"
    )
    assert "\n" not in str(err.value)


@pytest.mark.parametrize("layout", LAYOUTS)
@pytest.mark.parametrize("algorithm", RECIPE_ALGORITHMS)
def test_each_named_recipe_is_what_train_py_composes(algorithm, layout):
    """Over SafetyOptions' and off_policy.yaml's values, ``algo=<algorithm> env=<layout>``
    sets exactly ``recipe_options(algorithm, layout)``, every key (a WCSAC variant's
    ``risk_level`` is the run's own, not the recipe's)."""
    algo = OmegaConf.to_container(_composed(algorithm, layout).algo, resolve=True)
    base = _base()
    now = _flat(algo)
    wcsac = algo["name"] == "wcsac"
    ignored = NOT_RECIPE | ({"risk_level"} if wcsac else set())
    differing = {k: v for k, v in now.items() if k not in ignored and v != base.get(k)}
    recipe = _flat(dict(recipe_options(algorithm, layout)))
    assert "risk_level" not in recipe or not wcsac
    assert differing == {k: v for k, v in recipe.items() if v != base.get(k)}


@pytest.mark.parametrize("layout", LAYOUTS)
def test_the_kit_and_paper_objects_are_their_recipes(layout):
    assert kit_options(layout) == recipe_options("wcsac", layout)
    assert KIT_OPTIONS == kit_options("static")
    # the paper's recipe is the schema's defaults: its file sets nothing over them but
    # the authors' κ advice on the harder layouts, and PAPER_OPTIONS are those defaults
    paper = recipe_options("wcsac_paper", layout)
    harder = layout in ("dynamic", "point_goal1", "point_goal2")
    assert set(paper) == ({"kappa_lr_scale", "damp_scale"} if harder else set())
    assert dict(PAPER_OPTIONS) == {k: getattr(SafetyOptions(), k) for k in PAPER_OPTIONS}


def _same_parts(loss, parts: dict) -> None:
    assert loss.head_options == parts["safety_head"]
    assert loss.signal_options == parts["signal"]
    assert type(loss.constraint) is type(parts["constraint"])
    assert repr(loss.constraint) == repr(parts["constraint"])
    assert float(loss.kappa) == float(parts["constraint"].kappa)
    assert float(loss.log_alpha.exp()) == pytest.approx(parts["alpha_init"], rel=1e-6)


@pytest.mark.parametrize("layout", ["static", "dynamic", "point_goal1"])
@pytest.mark.parametrize("algorithm", RECIPE_ALGORITHMS)
def test_the_trainers_loss_is_the_named_recipes_loss(algorithm, layout):
    """``make_loss`` on the composed config gives the parts ``loss_parts`` gives for the
    named recipe (with the recipe's safety critic), so a user's own loop with the named
    object runs the loss ``train.py`` runs."""
    from wcsac_rl.envs import make_env
    from wcsac_rl.training import builders

    cfg = _composed(algorithm, layout)
    env = make_env("tiny", seed=0)  # (the layout's recipe on the tiny env's networks)
    try:
        loss = builders.make_loss(cfg, builders.make_agent(cfg, env), 100)
    finally:
        env.close()
    _same_parts(loss, loss_parts(recipe_options(algorithm, layout)))
    recipe = recipe_options(algorithm, layout)
    assert loss.risk_level == (0.1 if cfg.algo.name == "wcsac" else 1.0)
    assert (
        loss.safety_critic_kind
        == {
            "iqn": "iqn",
            "gaussian": "gaussian" if recipe.get("variance", True) else "mean",
        }[recipe.get("safety_critic", "gaussian")]
    )


@pytest.mark.parametrize(
    "algo, parts", [("wcsac", None), ("wcsac_paper", "defaults")], ids=["kit", "paper"]
)
def test_the_loss_a_user_builds_is_what_train_py_builds(algo, parts):
    """``WCSACLoss(actor, qvalue, safety_critic, risk_level=..., cost_limit=...,
    **loss_parts(KIT_OPTIONS))`` with the kit's IQN critic is what ``train.py algo=wcsac
    env=static`` builds; with no parts, the loss's defaults, it is what ``train.py
    algo=wcsac_paper env=static`` builds."""
    from wcsac_rl.envs import make_env
    from wcsac_rl.training import builders

    cfg = _composed(algo, "static")
    env = make_env("tiny", seed=0)
    try:
        agent = builders.make_agent(cfg, env)
        trained = builders.make_loss(cfg, agent, 1000)
    finally:
        env.close()
    given = loss_parts(KIT_OPTIONS) if parts is None else {}
    plain = WCSACLoss(
        agent.actor, agent.qvalues, agent.safety, risk_level=0.1, cost_limit=15.0, **given
    )
    expected = loss_parts(KIT_OPTIONS if parts is None else PAPER_OPTIONS)
    _same_parts(plain, expected)
    _same_parts(trained, expected)
    for name in ("risk_level", "cost_limit", "max_episode_steps", "cost_gamma", "cost_n_steps"):
        assert getattr(plain, name) == getattr(trained, name), name
    assert plain.safety_critic_kind == trained.safety_critic_kind
    assert float(plain.cost_threshold) == float(trained.cost_threshold)
    assert float(plain.target_entropy) == float(trained.target_entropy)
    assert plain.loss_function == trained.loss_function == "l2"
    assert math.isclose(float(plain.kappa), math.log(2.0), rel_tol=1e-6)
    assert torch.equal(plain.log_alpha, trained.log_alpha)


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (
            lambda: recipe_options("wcsac_fast"),
            "no recipe for algorithm 'wcsac_fast': the algorithms with a safety critic are "
            + ", ".join(RECIPE_ALGORITHMS),
        ),
        (
            lambda: kit_options("moon"),
            "no layout 'moon': the layouts are " + ", ".join(LAYOUTS),
        ),
        (
            lambda: loss_parts({"kapa_init": 1.0}),
            "unknown option 'kapa_init' in the recipe: not a SafetyOptions field nor one of "
            "the trainer's (" + ", ".join(TRAINER_KEYS) + ")",
        ),
        (lambda: loss_parts({"pid": {"kq": 1.0}}), "unknown option pid.kq in the recipe"),
        (
            lambda: loss_parts({"kappa_init": -1.0}),
            "kappa_init must be in [0, 1e+06] (a number), got -1.0",
        ),
    ],
    ids=["algorithm", "layout", "option", "gain", "value"],
)
def test_a_bad_recipe_is_one_line_naming_it(call, message):
    with pytest.raises(ValueError) as err:
        call()
    assert str(err.value) == message
