"""A bad ensemble option is one line naming it, and no run directory is left behind: through
``make_trainer`` (the composed config) and through ``train.py`` (one ``error:`` line on
stderr, exit code 1). The loss's own refusals are in tests/test_ensemble_reading.py."""

from __future__ import annotations

import re
import subprocess
import sys

import pytest
from _training_helpers import ROOT, compose_config

from wcsac_rl.training import ConfigError, make_trainer
from wcsac_rl.training.config_keys import check_override_keys

BAD = [
    (
        ["algo.num_safety_nets=1", "algo.ensemble_reading=ucb"],
        "algo.ensemble_reading=ucb reads an ensemble of safety critics: it needs "
        "algo.num_safety_nets >= 2, got 1",
    ),
    (
        ["algo.safety_critic=iqn", "algo.num_safety_nets=1", "algo.ensemble_reading=tqc"],
        "algo.ensemble_reading=tqc reads an ensemble of safety critics: it needs "
        "algo.num_safety_nets >= 2, got 1",
    ),
    (
        ["algo=cal", "algo.num_safety_nets=1"],  # CAL's recipe reads a UCB
        "algo.ensemble_reading=ucb reads an ensemble of safety critics: it needs "
        "algo.num_safety_nets >= 2, got 1",
    ),
    (
        ["algo.num_safety_nets=4", "algo.ensemble_reading=ucb", "algo.k_ucb=-0.5"],
        "algo.k_ucb must be in [0, 1e+06] (a number), got -0.5",
    ),
    (["algo=cal", "algo.k_ucb=-1"], "algo.k_ucb must be in [0, 1e+06] (a number), got -1"),
    (
        ["algo.num_safety_nets=4", "algo.prior_scale=-1"],
        "algo.prior_scale must be in [0, 1e+06] (a number), got -1",
    ),
    (
        ["algo.prior_scale=0.5"],
        "algo.prior_scale > 0 reads an ensemble of safety critics: it needs "
        "algo.num_safety_nets >= 2, got 1",
    ),
]

NO_SAFETY_CRITIC = (
    "unknown config key algo.{key}: an option of the safety critic and κ, which the "
    "algo={algo}{where} config does not have (algo=sac_lag, cal and wcsac do)"
)
ENSEMBLE_KEYS = [
    "num_safety_nets=4",
    "ensemble_target=max",
    "ensemble_reading=ucb",
    "k_ucb=1",
    "k_ucb_lr=0.01",
    "k_ucb_max=2",
    "prior_scale=1",
]


@pytest.mark.parametrize(("overrides", "line"), BAD, ids=[" ".join(o) for o, _ in BAD])
def test_a_bad_ensemble_value_is_one_line_and_no_run_directory(tmp_path, overrides, line):
    with pytest.raises(ConfigError) as error:
        make_trainer(compose_config("env=tiny", *overrides), tmp_path / "run")
    assert str(error.value) == line
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("algo", ["sac", "cpo", "random"])
@pytest.mark.parametrize("option", ENSEMBLE_KEYS)
def test_an_ensemble_option_for_an_algorithm_without_a_safety_critic(tmp_path, algo, option):
    key = option.split("=")[0]
    line = NO_SAFETY_CRITIC.format(key=key, algo=algo, where="")
    with pytest.raises(ConfigError, match=f"^{re.escape(line)}$"):  # the command line's check
        check_override_keys([f"algo={algo}", f"algo.{option}"])
    if algo == "cpo":
        return  # (CPO's schedule keys are not the test helper's: its composed check is the same)
    composed = compose_config("env=tiny", f"algo={algo}", f"+algo.{option}")
    line = NO_SAFETY_CRITIC.format(key=key, algo=algo, where=" env=tiny logger=csv")
    with pytest.raises(ConfigError, match=f"^{re.escape(line)}$"):
        make_trainer(composed, tmp_path / "run")
    assert not (tmp_path / "run").exists()


CLI = [
    (
        ["algo.ensemble_reading=ucb"],
        "error: algo.ensemble_reading=ucb reads an ensemble of safety critics: it needs "
        "algo.num_safety_nets >= 2, got 1",
    ),
    (
        ["algo.num_safety_nets=4", "algo.ensemble_reading=ucb", "algo.k_ucb=-1"],
        "error: algo.k_ucb must be in [0, 1e+06] (a number), got -1",
    ),
    (
        ["algo.num_safety_nets=4", "algo.prior_scale=-0.5"],
        "error: algo.prior_scale must be in [0, 1e+06] (a number), got -0.5",
    ),
    (
        ["algo=sac", "algo.num_safety_nets=4"],
        "error: unknown config key algo.num_safety_nets: an option of the safety critic and "
        "κ, which the env=tiny algo=sac config does not have (algo=sac_lag, cal and wcsac do)",
    ),
]


@pytest.mark.parametrize(("overrides", "line"), CLI, ids=[" ".join(o) for o, _ in CLI])
def test_train_py_refuses_a_bad_ensemble_option_in_one_line(tmp_path, overrides, line):
    result = subprocess.run(
        [
            sys.executable,
            str(ROOT / "train.py"),
            "env=tiny",
            *overrides,
            f"hydra.run.dir={tmp_path / 'r'}",
        ],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert result.returncode == 1 and "Traceback" not in result.stderr
    assert result.stderr.strip().splitlines() == [line]
    assert not (tmp_path / "r").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # nothing else either
