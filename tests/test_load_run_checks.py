"""What ``load_run`` (and so evaluate, calibration and Figure 5) is given and what it reads
from a run is checked before anything is built: its own arguments, the stored config's
sizes, and that the checkpoint is the run's own (an algorithm changed in the checkpoint
would otherwise be evaluated under the run's label)."""

from __future__ import annotations

import shutil

import pytest
import torch
from _hostile_helpers import train_tiny

from wcsac_rl import load_run
from wcsac_rl.training import ConfigError


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    return train_tiny(tmp_path_factory.mktemp("load_run") / "run", "total_frames=400")


def _tampered(tiny_run, tmp_path, edit):
    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    path = run / "checkpoints" / "last.pt"
    checkpoint = torch.load(path, weights_only=True)
    edit(checkpoint["config"])
    torch.save(checkpoint, path)
    return run


@pytest.mark.parametrize(
    ("keywords", "words"),
    [
        ({"seed": "abc"}, "seed must be a whole number or None, got 'abc'"),  # LR3
        ({"num_envs": 2.5}, "num_envs must be a whole number >= 1, got 2.5"),  # LR2
        ({"num_envs": True}, "num_envs must be a whole number >= 1, got True"),  # LR2
        ({"num_envs": 0}, "num_envs must be a whole number >= 1, got 0"),
    ],
)
def test_load_run_arguments_are_checked_first(tiny_run, keywords, words):
    with pytest.raises(ConfigError) as err:
        load_run(tiny_run, **keywords)
    assert str(err.value) == f"load_run: {words}"


def test_a_stored_width_that_is_not_a_number_is_one_line(tiny_run, tmp_path):  # LC2
    run = _tampered(tiny_run, tmp_path, lambda c: c["algo"]["network"].update(width="wide"))
    with pytest.raises(ConfigError) as err:
        load_run(run)
    assert "algo.network.width must be an integer in [1, 16384], got 'wide'" in str(err.value)


def test_a_checkpoint_whose_algorithm_is_not_the_runs_is_refused(tiny_run, tmp_path):  # LC5
    run = _tampered(tiny_run, tmp_path, lambda c: c["algo"].update(name="random"))
    with pytest.raises(ConfigError) as err:
        load_run(run)
    message = str(err.value)
    assert "does not belong to the run" in message and "\n" not in message
    assert "algo.name: checkpoint='random'" in message
