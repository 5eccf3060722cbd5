"""A resume checks what it restores: a loss entry made from the run's config (γ, the
cost threshold, β's start, the target entropy) must be what the config gives, target
networks and optimizer moments must be finite; otherwise one line naming the entry, and
nothing is loaded (red-team C1-C4: γ 0.5 or a threshold of 1e9 trained on silently)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
import torch
from _hostile_helpers import train_tiny
from _loss_helpers import make_batch, make_loss
from _training_helpers import ROOT

from wcsac_rl.training.checkpoint import (
    CONFIG_DERIVED,
    StateMismatch,
    load_module_state,
    load_optimizer_state,
)


def _loss():
    loss = make_loss()
    loss.make_value_estimator(gamma=0.99)
    return loss


@pytest.mark.parametrize("key", CONFIG_DERIVED)
def test_an_entry_made_from_the_config_must_be_what_the_config_gives(key):
    loss, other = _loss(), _loss()
    state = loss.state_dict()
    assert key in state
    load_module_state(other, state)  # (as saved: loads)
    before = {k: v.clone() for k, v in other.state_dict().items()}
    state[key] = state[key] * 0.5 + 1.0
    with pytest.raises(StateMismatch) as err:
        load_module_state(other, state)
    assert str(err.value).startswith(f"its {key} is ") and "\n" not in str(err.value)
    assert all(torch.equal(v, before[k]) for k, v in other.state_dict().items())


def test_non_finite_target_networks_are_refused_by_name():
    loss = _loss()
    state = loss.state_dict()
    key = next(k for k in state if k.startswith("target_qvalue_network_params"))
    state[key] = torch.full_like(state[key], float("nan"))
    with pytest.raises(StateMismatch, match=f"non-finite weights: {key} has"):
        load_module_state(_loss(), state)


def test_non_finite_optimizer_moments_are_refused():
    loss = _loss()
    optim = torch.optim.Adam(loss.parameters(), lr=1e-3)
    out = loss(make_batch())
    sum(v for k, v in out.items() if k.startswith("loss_")).backward()
    optim.step()
    state = optim.state_dict()
    fresh = torch.optim.Adam(loss.parameters(), lr=1e-3)
    load_optimizer_state(fresh, state)  # (finite: loads)
    state["state"][0]["exp_avg"] = torch.full_like(state["state"][0]["exp_avg"], float("nan"))
    with pytest.raises(StateMismatch, match="optimizer state holds non-finite values"):
        load_optimizer_state(torch.optim.Adam(loss.parameters(), lr=1e-3), state)


def test_train_py_refuses_to_resume_a_checkpoint_whose_threshold_was_edited(tmp_path):
    """C2 end to end: the constraint would have been off for the rest of the run."""
    run = train_tiny(tmp_path / "run", "total_frames=400")
    path = run / "checkpoints" / "last.pt"
    checkpoint = torch.load(path, weights_only=True)
    checkpoint["learner"]["loss"]["cost_threshold"] = torch.tensor(1e9)
    torch.save(checkpoint, path)
    done = subprocess.run(
        [sys.executable, str(ROOT / "train.py"), f"resume={run}", "total_frames=800"],
        capture_output=True, text=True, timeout=300, cwd=tmp_path,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
    )  # fmt: skip
    assert done.returncode != 0 and "Traceback" not in done.stderr
    errors = [line for line in done.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "its cost_threshold is 1000000000.0" in errors[0]


@pytest.fixture(scope="module")
def tiny_checkpoint(tmp_path_factory):
    run = train_tiny(tmp_path_factory.mktemp("counters") / "run", "total_frames=400")
    return run, torch.load(run / "checkpoints" / "last.pt", weights_only=True)


TAMPERED_COUNTERS = [
    (("epoch_progress", "costs"), ["abc"], "epoch_progress.costs must be a list of numbers"),  # C5
    (("epoch_progress", "returns"), [float("nan")], "epoch_progress.returns must be a list"),
    (("epoch_progress", "start_frames"), 10**9, "epoch_progress.start_frames must be at most"),
    (("training_safety", "epochs_over_limit"), -5, "training_safety.epochs_over_limit must be a whole number >= 0"),  # C6
    (("training_safety", "epochs_over_limit"), 10**6, "training_safety.epochs_over_limit must be at most its 'epochs'"),
    (("updates",), -1, "its 'updates' entry must be a whole number >= 0"),
    (("epoch",), 2.5, "its 'epoch' entry must be a whole number >= 0"),
]  # fmt: skip


@pytest.mark.parametrize(("where", "value", "words"), TAMPERED_COUNTERS)
def test_a_counter_the_trainer_could_not_have_written_is_refused(
    tiny_checkpoint, where, value, words
):
    from wcsac_rl.training import ConfigError
    from wcsac_rl.training.checkpoint import check_counters

    _, saved = tiny_checkpoint
    check_counters(saved, "last.pt")  # (as written: accepted)
    state = {**saved, **{k: dict(saved[k]) for k in ("epoch_progress", "training_safety")}}
    node = state
    for key in where[:-1]:
        node = node[key]
    node[where[-1]] = value
    with pytest.raises(ConfigError) as err:
        check_counters(state, "last.pt")
    assert words in str(err.value) and "\n" not in str(err.value)


def test_train_py_refuses_a_tampered_counter_before_writing_anything(tiny_checkpoint, tmp_path):
    """C5 end to end: no traceback, and the resume records nothing."""
    import shutil

    run = tmp_path / "run"
    shutil.copytree(tiny_checkpoint[0], run)
    path = run / "checkpoints" / "last.pt"
    checkpoint = torch.load(path, weights_only=True)
    checkpoint["epoch_progress"]["costs"] = ["abc"]
    torch.save(checkpoint, path)
    before = sorted(p.name for p in run.iterdir())
    done = subprocess.run(
        [sys.executable, str(ROOT / "train.py"), f"resume={run}", "total_frames=800"],
        capture_output=True, text=True, timeout=300, cwd=tmp_path,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
    )  # fmt: skip
    assert done.returncode == 1 and "Traceback" not in done.stderr
    errors = [line for line in done.stderr.splitlines() if line.strip()]
    assert len(errors) == 1 and "epoch_progress.costs must be" in errors[0], errors
    assert sorted(p.name for p in run.iterdir()) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]
