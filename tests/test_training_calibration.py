"""The safety critic's reading of the training episodes against their realised cost-to-go
(``train_calib/*``, :mod:`wcsac_rl.training.training_calibration`): hand-computed episodes,
episodes joined across batches and envs, and the columns of a tiny training run.

Tolerances: the readings are float32 numbers chosen exact in binary (0.5, 0.25, 3) and the
sums are float64, so the expected values are exact up to float64 rounding (``rel=1e-12``).
"""

from __future__ import annotations

import csv
import math
from types import SimpleNamespace

import pytest
import torch
from _training_helpers import compose_config
from tensordict import TensorDict

from wcsac_rl.training import make_trainer
from wcsac_rl.training.training_calibration import (
    TRAINING_CALIBRATION_KEYS,
    TrainingCalibration,
)

F64 = 1e-12


class _ReadsTheObservation:
    """A stand-in loss whose critic reads Γ = the observation's first entry (so a test
    sets every reading), with γ_c and α as given."""

    def __init__(self, cost_gamma: float, risk_level: float) -> None:
        self.cost_gamma, self.risk_level = cost_gamma, risk_level
        self.tensor_keys = SimpleNamespace(action="action", cost="cost")
        self.safety_network = SimpleNamespace(in_keys=["observation", "action"])
        self.read = 0

    def safety_estimates(self, td):
        self.read += td.numel()
        return TensorDict({"cvar": td["observation"][..., 0]}, batch_size=td.batch_size)


def _steps(readings, costs, dones, step_counts) -> TensorDict:
    """One env's collected steps ``[T]`` in the collector's layout."""
    n = len(readings)
    return TensorDict(
        {
            "observation": torch.tensor(readings, dtype=torch.float32).reshape(n, 1),
            "action": torch.zeros(n, 1),
            "step_count": torch.tensor(step_counts).reshape(n, 1),
            "next": {
                "cost": torch.tensor(costs, dtype=torch.float32).reshape(n, 1),
                "done": torch.tensor(dones).reshape(n, 1),
            },
        },
        batch_size=[n],
    )


# γ_c = 0.5, d = 1. Batch 1: the end of an episode seen without its start (ignored), then
# episode A (costs 0, 2: G = 1, 2; cost 2 > d) and the first step of episode B.
# Batch 2: the rest of B (costs 1, 0, 0: G = 1, 0, 0; cost 1, not over d) and the first
# step of C, which has not ended.
FIRST = _steps(
    [9.0, 0.5, 0.25, 3.0], [5.0, 0.0, 2.0, 1.0], [True, False, True, False], [7, 0, 1, 0]
)
SECOND = _steps([0.0, 0.0, 4.0], [0.0, 0.0, 1.0], [False, True, False], [1, 2, 0])
EXPECTED = {
    "train_calib/episodes": 2,
    "train_calib/start_cvar": (0.5 + 3.0) / 2,
    "train_calib/start_cost_to_go": (1.0 + 1.0) / 2,
    "train_calib/start_realised_cvar": 1.0,  # the worst ⌈2·0.5⌉ = 1 of G_0 = 1, 1
    "train_calib/start_ratio": 1.75,
    "train_calib/over_episodes": 1,
    "train_calib/over_cvar": (0.5 + 0.25) / 2,
    "train_calib/over_cost_to_go": (1.0 + 2.0) / 2,
    "train_calib/over_ratio": 0.375 / 1.5,
}


def test_the_readings_and_the_realised_cost_to_go_of_hand_computed_episodes():
    loss = _ReadsTheObservation(cost_gamma=0.5, risk_level=0.5)
    calibration = TrainingCalibration(loss, cost_limit=1.0)
    calibration.add(FIRST)
    calibration.add(SECOND)
    assert loss.read == 7  # every collected step is read once
    metrics = calibration.epoch_metrics()
    assert list(metrics) == list(TRAINING_CALIBRATION_KEYS)
    assert metrics == pytest.approx(EXPECTED, rel=F64)
    # a new epoch: nothing has ended in it yet; C ends in it, seen from its start
    empty = calibration.epoch_metrics()
    assert empty["train_calib/episodes"] == 0 and empty["train_calib/over_episodes"] == 0
    assert all(math.isnan(v) for k, v in empty.items() if not k.endswith("episodes"))
    calibration.add(_steps([1.0], [0.0], [True], [1]))
    again = calibration.epoch_metrics()
    assert again["train_calib/episodes"] == 1
    assert again["train_calib/start_cvar"] == 4.0
    assert again["train_calib/start_cost_to_go"] == pytest.approx(1.0, rel=F64)  # 1 + 0.5·0


def test_envs_side_by_side_are_separate_episodes():
    """``[num_envs, time]``: env 0 holds the hand example's first batch, env 1 one
    one-step episode of cost 3 (> d) read at 0.25; each env's steps are joined in time."""
    loss = _ReadsTheObservation(cost_gamma=0.5, risk_level=0.5)
    calibration = TrainingCalibration(loss, cost_limit=1.0)
    other = _steps([0.25, 0.0, 0.0, 0.0], [3.0, 0.0, 0.0, 0.0], [True] * 4, [0, 5, 5, 5])
    calibration.add(torch.stack([FIRST, other]))
    calibration.add(torch.stack([SECOND, _steps([0.0] * 3, [0.0] * 3, [True] * 3, [5] * 3)]))
    metrics = calibration.epoch_metrics()
    assert metrics["train_calib/episodes"] == 3
    assert metrics["train_calib/start_cvar"] == pytest.approx((0.5 + 3.0 + 0.25) / 3, rel=F64)
    # the worst ⌈3·0.5⌉ = 2 of G_0 = 1, 1, 3
    assert metrics["train_calib/start_realised_cvar"] == pytest.approx(2.0, rel=F64)
    assert metrics["train_calib/over_episodes"] == 2
    assert metrics["train_calib/over_cvar"] == pytest.approx((0.5 + 0.25 + 0.25) / 3, rel=F64)
    assert metrics["train_calib/over_cost_to_go"] == pytest.approx((1.0 + 2.0 + 3.0) / 3, rel=F64)


def test_the_epoch_so_far_round_trips_and_running_episodes_are_dropped():
    loss = _ReadsTheObservation(cost_gamma=0.5, risk_level=0.5)
    calibration = TrainingCalibration(loss, cost_limit=1.0)
    calibration.add(FIRST)  # A has ended; B is running
    restored = TrainingCalibration(loss, cost_limit=1.0)
    restored.load_state_dict(calibration.state_dict())
    restored.add(SECOND)  # B's end, seen without its start by the resumed session
    metrics = restored.epoch_metrics()
    assert metrics["train_calib/episodes"] == 1
    assert metrics["train_calib/start_cvar"] == 0.5
    assert metrics["train_calib/over_ratio"] == pytest.approx(0.25, rel=F64)


def test_a_batch_without_episode_starts_is_refused_naming_what_is_missing():
    calibration = TrainingCalibration(_ReadsTheObservation(0.5, 0.5), cost_limit=1.0)
    with pytest.raises(KeyError, match="neither 'step_count' nor 'is_init'"):
        calibration.add(FIRST.exclude("step_count"))


@pytest.mark.parametrize("algo", ["wcsac", "sac_lag", "cal"])
def test_a_tiny_training_run_logs_the_columns(tmp_path, algo):
    trainer = make_trainer(
        compose_config("env=tiny", f"algo={algo}", "cost_limit=0"), tmp_path / "run"
    )
    try:
        trainer.run()
    finally:
        trainer.close()
    with (tmp_path / "run" / "progress.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 2
    for row in rows:
        assert set(TRAINING_CALIBRATION_KEYS) <= set(row)
        # every training episode of a fresh run is seen from its start
        episodes = int(float(row["train_calib/episodes"]))
        assert episodes == int(float(row["train/episodes"])) >= 1
        over = int(float(row["train_calib/over_episodes"]))
        # d = 0: an episode that paid any cost is over d
        assert 0 <= over <= episodes
        assert math.isfinite(float(row["train_calib/start_cvar"]))
        assert float(row["train_calib/start_cost_to_go"]) >= 0.0
        if over:
            assert float(row["train_calib/over_cost_to_go"]) > 0.0


def test_sac_has_no_safety_critic_and_no_columns(tmp_path):
    trainer = make_trainer(compose_config("env=tiny", "algo=sac"), tmp_path / "run")
    try:
        trainer.run()
    finally:
        trainer.close()
    with (tmp_path / "run" / "progress.csv").open(newline="") as f:
        header = next(csv.reader(f))
    assert not any(key.startswith("train_calib/") for key in header)


def test_training_calibration_does_not_change_the_training(tmp_path, monkeypatch):
    """The readings take no gradient and draw no random numbers: a run without them
    logs the same numbers in every other column."""
    from wcsac_rl.training import off_policy

    def run(name):
        trainer = make_trainer(compose_config("env=tiny"), tmp_path / name)
        try:
            trainer.run()
        finally:
            trainer.close()
        with (tmp_path / name / "progress.csv").open(newline="") as f:
            return list(csv.DictReader(f))

    read = run("read")
    monkeypatch.setattr(off_policy, "supports_calibration", lambda loss: False)
    plain = run("plain")
    for got, want in zip(plain, read):
        assert not any(key.startswith("train_calib/") for key in got)
        for key, value in got.items():
            if not key.startswith("time"):
                assert value == want[key], key


# ------------------------------------------------------------- the calibration report
def _progress(path, rows):
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


def test_the_report_reads_the_columns_of_progress_csv(tmp_path):
    from wcsac_rl.evaluation.run_calibration import training_episode_readings

    assert training_episode_readings(tmp_path) == []  # no progress.csv
    _progress(tmp_path / "progress.csv", [{"frames": 400, "train/episode_cost": 3.0}])
    assert training_episode_readings(tmp_path) == []  # a run from before the columns
    first = {"frames": 400, **{k: v for k, v in EXPECTED.items()}}
    second = {"frames": 800, **dict.fromkeys(TRAINING_CALIBRATION_KEYS, "")}
    second["train_calib/episodes"] = second["train_calib/over_episodes"] = 0
    _progress(tmp_path / "progress.csv", [first, second])
    epochs = training_episode_readings(tmp_path)
    assert [e["frames"] for e in epochs] == [400.0, 800.0]
    assert epochs[0]["over_ratio"] == pytest.approx(0.25, rel=F64)
    assert epochs[0]["start_cvar"] == 1.75 and epochs[0]["episodes"] == 2
    assert epochs[1]["episodes"] == 0 and math.isnan(epochs[1]["start_cvar"])


def test_the_table_shows_the_epochs_over_d_and_the_last():
    from wcsac_rl.calibration import training_lines

    def epoch(frames, over, over_ratio):
        return {
            "frames": frames,
            "episodes": 4,
            "over_episodes": over,
            "start_cvar": 0.5,
            "start_cost_to_go": 1.0,
            "start_realised_cvar": 2.0,
            "start_ratio": 0.25,
            "over_cvar": 1.0 if over else math.nan,
            "over_cost_to_go": 4.0 if over else math.nan,
            "over_ratio": over_ratio,
        }

    result = {
        "cost_limit": 1.0,
        "training_episodes": [
            epoch(400, 0, math.nan),
            epoch(800, 2, 0.25),
            epoch(1200, 0, math.nan),
        ],
    }
    lines = training_lines(result)
    assert lines[0] == (
        "training episodes, read when collected (1 of 3 epochs had episodes over d = 1; "
        "the last epoch too)"
    )
    rows = [line.split() for line in lines[2:-1]]
    assert rows == [
        ["800", "4", "2", "0.500", "2.000", "0.250", "1.000", "4.000", "0.250"],
        ["1200", "4", "0", "0.500", "2.000", "0.250", "—", "—", "—"],
    ]
    assert training_lines({"cost_limit": 1.0})[0].startswith("training episodes: not logged")
