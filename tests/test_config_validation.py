"""Every bad config value is one line naming the key and what it may be, before anything is
built; a key no config has is refused naming the closest known key; every
legitimate config (the presets, the rows, the experiments, the tests' own) still passes."""

from __future__ import annotations

import re
import subprocess
import sys

import pytest
from _training_helpers import CONF, ROOT, TINY_CPO, compose_config

from wcsac_rl.training import ConfigError, make_trainer, validate_config
from wcsac_rl.training.config_keys import check_known_keys, check_override_keys

BAD_VALUES = [
    ("algo.lr=abc", "algo.lr must be > 0 (a number), got 'abc'"),
    ("algo.lr=nan", "algo.lr must be > 0 (a number), got nan"),
    ("algo.lr=inf", "algo.lr must be > 0 (a number), got inf"),
    ("algo.tau=abc", "algo.tau must be in (0, 1] (a number), got 'abc'"),
    ("algo.gamma=1.5", "algo.gamma must be in [0, 1] (a number), got 1.5"),
    ("algo.collector.utd_ratio=abc", "algo.collector.utd_ratio must be > 0 (a number)"),
    ("algo.target_entropy=abc", "algo.target_entropy must be auto (-|A|) or a finite number"),
    ("algo.network.width=0", "algo.network.width must be an integer in [1, 16384], got 0"),
    ("algo.network.depth=-1", "algo.network.depth must be an integer in [0, 64], got -1"),
    ("algo.network.activation=foo", "algo.network.activation must be one of relu, tanh"),
    (
        "algo.network.log_std_min=5",
        "algo.network.log_std_min (5) must be < algo.network.log_std_max (2)",
    ),
    ("algo.alpha_init=-1", "algo.alpha_init must be in (0, 1e+06] (a number), got -1"),
    ("algo.alpha_init=0", "algo.alpha_init must be in (0, 1e+06] (a number), got 0"),
    ("algo.kappa_init=abc", "algo.kappa_init must be in [0, 1e+06] (a number), got 'abc'"),
    ("algo.cost_gamma=abc", "algo.cost_gamma must be null or in [0, 1] (a number), got 'abc'"),
    ("algo.variance=3", "algo.variance must be true or false, got 3"),
    ("algo.iqn.huber_kappa=x", "algo.iqn.huber_kappa must be in (0, 1e+06] (a number), got 'x'"),
    ("algo.shield.candidates=1", "algo.shield.candidates must be 0 (no shield) or >= 2"),
    ("algo.shield.candidates=-2", "algo.shield.candidates must be an integer >= 0, got -2"),
    ("algo.shield.scale=0", "algo.shield.scale must be in (0, 1e+06] (a number), got 0"),
    (
        "+algo.shield.candidate=8",
        "unknown shield option algo.shield.candidate (did you mean algo.shield.candidates?)",
    ),
    ("algo.collector=4", "algo.collector must hold its options (a mapping), got 4"),
    ("seed=18446744073709551616", "seed must be at most 2**63 - 1 = 9223372036854775807"),
    ("risk_level=true", "risk_level α must be a number in (0, 1], got True"),
    ("risk_level=nan", "risk_level α must be a number in (0, 1], got nan"),
    ("cost_limit=nan", "cost_limit must be >= 0 (an episodic cost budget), got nan"),
    ("cost_limit=inf", "cost_limit must be >= 0 (an episodic cost budget), got inf"),
    ("algo.batch_size=20000", "algo.batch_size (20000) must be <= algo.buffer_size (10000)"),
    ("device=1", "device must be cpu, cuda[:N] or mps, got 1"),
    ("resume=3", "resume must be null, auto or a run directory, got 3"),
    ("env.kwargs=3", "env.kwargs must be a mapping of env arguments, got 3"),
    ("+risk_levl=0.1", "unknown config key risk_levl (did you mean risk_level?)"),
    ("+algo.batchsize=64", "unknown config key algo.batchsize (did you mean algo.batch_size?)"),
]


@pytest.mark.parametrize(("override", "message"), BAD_VALUES, ids=[o for o, _ in BAD_VALUES])
def test_a_bad_value_is_one_line_naming_the_key_before_anything_is_built(
    tmp_path, override, message
):
    with pytest.raises(ConfigError) as err:
        make_trainer(compose_config("env=tiny", override), tmp_path / "run")
    assert "\n" not in str(err.value)
    assert message in str(err.value)
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("algo.max_kl=abc", "algo.max_kl must be > 0 (a number), got 'abc'"),
        ("algo.network.log_std_init=x", "algo.network.log_std_init must be a finite number"),
        ("algo.value_batch_size=0", "algo.value_batch_size must be an integer > 0, got 0"),
        ("algo.normalize_advantage=3", "algo.normalize_advantage must be true or false, got 3"),
        ("+algo.kappa_init=1", "unknown config key algo.kappa_init"),  # a WCSAC key
    ],
)
def test_cpo_values_and_keys_are_checked_against_cpos_own_config(override, message):
    with pytest.raises(ConfigError, match=re.escape(message)):
        validate_config(compose_config(*TINY_CPO, override, small=False))


def _group_options(group: str) -> list[str]:
    return sorted(p.stem for p in (CONF / group).glob("*.yaml"))


@pytest.mark.parametrize("algo", _group_options("algo"))
@pytest.mark.parametrize("env", ["tiny", "static"])
def test_every_algo_preset_has_only_known_keys(algo, env):
    check_known_keys(compose_config(f"algo={algo}", f"env={env}", small=False))


@pytest.mark.parametrize("row", _group_options("row"))
def test_every_row_has_only_known_keys(row):
    validate_config(compose_config(f"+row={row}", "env=tiny", small=False))


@pytest.mark.parametrize("experiment", _group_options("experiment"))
def test_every_experiment_has_only_known_keys(experiment):
    check_known_keys(compose_config(f"experiment={experiment}", small=False))


def test_the_tests_small_schedules_and_env_kwargs_are_known():
    validate_config(compose_config("env=tiny", "+env.kwargs.hazard_xy=[0.0,0.2]"))
    validate_config(compose_config("env=tiny", "algo=random"))


@pytest.mark.parametrize(
    "overrides",
    [
        ["algo=cpo", "algo.max_kl=0.02"],
        ["+row=cpo", "algo.max_kl=0.02"],
        ["algo=wcsac,cpo", "algo.max_kl=0.02"],  # a sweep: a key of one of its configs
        ["experiment=quickstart", "seed=1", "hydra.run.dir=x", "hydra/launcher=local"],
        ["+env.kwargs.hazard_xy=[0.0,0.2]", "+new_key=1"],  # (+keys: checked once composed)
        ["algo.lr=abc"],  # a bad value of a known key: validate_config's
    ],
)
def test_command_lines_with_known_keys_pass_the_early_check(overrides):
    check_override_keys(overrides)


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (
            ["algo.batchsize=64"],
            "algo.batchsize (did you mean algo.batch_size?): not a key of the default",
        ),
        (["risk_levl=0.1"], "risk_levl (did you mean risk_level?)"),
        (
            ["algo=cpo", "algo.lr=0.1"],
            "algo.lr (did you mean algo.lmbda?): not a key of the algo=cpo",
        ),
        (["algo=cpo", "algo.network.widht=3"], "did you mean algo.network.width?"),
    ],
)
def test_an_override_of_a_key_no_config_has_is_one_line_naming_the_closest(overrides, message):
    with pytest.raises(ConfigError) as err:
        check_override_keys(overrides)
    assert "\n" not in str(err.value) and message in str(err.value)


def test_total_frames_not_a_whole_number_of_batches_says_it_is_rounded(tmp_path, capsys):
    trainer = make_trainer(
        compose_config("env=tiny", "algo=random", "total_frames=100"), tmp_path / "run"
    )
    trainer.close()
    out = capsys.readouterr().out
    assert "total_frames=100 is rounded up to 400 (whole collector batches of 400 frames)" in out


def test_train_py_refuses_an_unknown_key_in_one_line_before_hydra(tmp_path):
    result = subprocess.run(
        [
            sys.executable,
            str(ROOT / "train.py"),
            "algo.batchsize=64",
            f"hydra.run.dir={tmp_path / 'r'}",
        ],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert result.returncode == 1 and "Traceback" not in result.stderr
    assert result.stderr.strip().splitlines() == [
        "error: unknown config key algo.batchsize (did you mean algo.batch_size?): not a key "
        "of the default config (see conf/ for the keys)"
    ]
    assert not (tmp_path / "r").exists()
