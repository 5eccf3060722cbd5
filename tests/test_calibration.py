"""Safety-critic calibration: cost-to-go, metrics, per-epoch columns, curves panel and CLI."""

from __future__ import annotations

import csv
import json
import math
import shutil
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from _env_helpers import tiny_goal_seeker
from _evaluation_helpers import png_size
from _loss_helpers import flat_parts
from _training_helpers import ROOT, compose_config
from tensordict import TensorDict

from wcsac_rl.calibration import main as calibration_main
from wcsac_rl.envs import make_env
from wcsac_rl.evaluation.plots import (
    CALIBRATION_PANEL,
    SLACK_PANEL,
    plot_run_curves,
    run_curves_figure,
)
from wcsac_rl.evaluation.run_calibration import (
    CALIBRATION_KEYS,
    calibration_keys,
    calibration_metrics,
    compare_episodes,
    discounted_cost_to_go,
    supports_calibration,
)
from wcsac_rl.rollouts import critic_calibration as rollout_calibration
from wcsac_rl.rollouts.episodes import (
    EpisodeResult,
    RecordedEpisode,
    record_episodes,
    run_episodes,
)
from wcsac_rl.training import make_trainer

# Hand-made inputs below are exact in float32 and the metrics are computed in float64:
# the only error is float64 rounding of a few operations.
F64 = 1e-12


# ------------------------------------------------------------------ pure functions
def test_discounted_cost_to_go_matches_a_hand_computed_sequence():
    # G4 = 2, G3 = 0.9·2, G2 = 0.9·1.8, G1 = 1 + 0.9·1.62, G0 = 0.9·2.458
    expected = [2.2122, 2.458, 1.62, 1.8, 2.0]
    got = discounted_cost_to_go([0.0, 1.0, 0.0, 0.0, 2.0], 0.9)
    assert got.dtype == np.float64
    np.testing.assert_allclose(got, expected, rtol=F64, atol=0)
    np.testing.assert_array_equal(discounted_cost_to_go([3.0, 1.0], 1.0), [4.0, 1.0])
    np.testing.assert_array_equal(discounted_cost_to_go([3.0, 1.0], 0.0), [3.0, 1.0])


class StubLoss:
    """A loss whose safety critic reads its answers off the observation:
    Q^c = obs[0], V^c = obs[1], Γ = Q^c + 2√V^c; α = 0.5, γ_c = 0.5."""

    tensor_keys = SimpleNamespace(action="action", cost="cost")
    risk_level = 0.5
    cost_gamma = 0.5

    def __init__(self, variance: bool = True) -> None:
        self.has_variance = variance
        self.seen: list[TensorDict] = []

    def safety_estimates(self, td):
        self.seen.append(td)
        q, v = td["observation"][..., 0], td["observation"][..., 1]
        out = {"cost_value": q, "cvar": q + 2 * v.sqrt()}
        if self.has_variance:
            out["cost_variance"] = v
        return TensorDict(out, batch_size=td.batch_size)


def _episode(cost_value, variance, costs) -> RecordedEpisode:
    n = len(costs)
    steps = TensorDict(
        {
            "observation": torch.tensor([cost_value, variance], dtype=torch.float32).T,
            "action": torch.zeros(n, 2),
            "next": {"cost": torch.tensor(costs, dtype=torch.float32).unsqueeze(-1)},
        },
        [n],
    )
    result = EpisodeResult(
        ret=0.0, cost=float(sum(costs)), length=n, goal_reached=0, numerical_failure=False
    )
    return RecordedEpisode(result, steps)


# With γ_c = 0.5 the realised cost-to-go of each episode is:
#   [0, 2] -> [1, 2];  [4] -> [4];  [0, 0, 0] -> [0, 0, 0];  [1, 0, 0, 8] -> [2, 2, 4, 8]
EPISODES = (
    ([0.5, 1.5], [1.0, 4.0], [0.0, 2.0]),
    ([3.0], [0.25], [4.0]),
    ([-1.0, 0.0, -0.5], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]),
    ([1.0, 2.0, 3.0, 6.0], [1.0, 1.0, 1.0, 1.0], [1.0, 0.0, 0.0, 8.0]),
)


def test_metrics_of_hand_made_episodes_match_closed_form_values():
    loss = StubLoss()
    m = calibration_metrics([_episode(*e) for e in EPISODES], loss)
    assert list(m) == list(CALIBRATION_KEYS)
    # the critic is asked once, on the root entries of all 10 steps (no "next")
    assert len(loss.seen) == 1 and loss.seen[0].batch_size == torch.Size([10])
    assert "next" not in loss.seen[0].keys()
    expected = {
        # start states: Q^c (0.5, 3, -1, 1), √V^c (1, 0.5, 0, 1), Γ (2.5, 4, -1, 3)
        "calib/start_cost_value": 3.5 / 4,
        "calib/start_std": 2.5 / 4,
        "calib/start_cvar": 8.5 / 4,
        # realised from s0: (1, 4, 0, 2); CVaR_0.5 = mean of the worst 2 = (4 + 2) / 2
        "calib/start_realised_cost_to_go": 7 / 4,
        "calib/start_realised_cvar": 3.0,
        "calib/start_cvar_ratio": (8.5 / 4) / 3.0,
        # sample std of (1, 4, 0, 2): squared deviations sum to 8.75, over n - 1 = 3
        "calib/realised_spread": math.sqrt(8.75 / 3),
        # 10 states: ΣQ^c = 15.5, Σ√V^c = 7.5, ΣG = 23, two Q^c < 0 (0 is not)
        "calib/mean_cost_value": 1.55,
        "calib/mean_std": 0.75,
        "calib/mean_cvar": (15.5 + 2 * 7.5) / 10,
        "calib/mean_realised_cost_to_go": 2.3,
        "calib/negative_share": 0.2,
        # episodic costs (2, 4, 0, 9): mean 15 / 4, CVaR_0.5 = (9 + 4) / 2
        "calib/episode_cost": 3.75,
        "calib/episode_cvar": 6.5,
    }
    for key, value in expected.items():
        assert m[key] == pytest.approx(value, rel=F64, abs=F64), key
    q = [0.5, 1.5, 3, -1, 0, -0.5, 1, 2, 3, 6]
    g = [1, 2, 4, 0, 0, 0, 2, 2, 4, 8]
    assert m["calib/correlation"] == pytest.approx(np.corrcoef(q, g)[0, 1], rel=F64)
    # the start-state Gaussians N(Q^c, V^c) mixed, CVaR_0.5 by an independent route:
    # scipy's root of the tail mass, then Rockafellar–Uryasev (the σ = 0 start state
    # is an atom, held at σ = 1e-6 as the kit does)
    from scipy import optimize, stats

    mu, sd = np.array([0.5, 3.0, -1.0, 1.0]), np.array([1.0, 0.5, 1e-6, 1.0])
    var = optimize.brentq(lambda v: stats.norm.sf((v - mu) / sd).mean() - 0.5, -20, 20)
    z = (var - mu) / sd
    tail = var + (sd * stats.norm.pdf(z) + (mu - var) * stats.norm.sf(z)).mean() / 0.5
    # bisection over a bracket of width ~25 in 50 halvings, float64 throughout
    assert m["calib/start_tail_cvar"] == pytest.approx(tail, abs=1e-9)
    assert m["calib/start_tail_ratio"] == pytest.approx(tail / 3.0, abs=1e-9)
    assert m["calib/start_tail_cvar"] >= m["calib/start_cost_value"]


@pytest.mark.parametrize("nonnegative", [False, True])
def test_start_tail_of_an_iqn_critic_pools_the_start_state_quantiles(nonnegative):
    from wcsac_rl.evaluation.run_calibration import EpisodeCalibration, summarize_calibration

    def episode(start_quantiles):
        quantiles = np.array([start_quantiles, [0.0, 0.0, 0.0, 0.0]])
        return EpisodeCalibration(
            cost=np.array([0.0, 1.0]),
            cost_to_go=np.array([0.5, 1.0]),
            cost_value=quantiles.mean(1),
            cvar=quantiles.max(1),
            std=quantiles.std(1),
            quantiles=quantiles,
        )

    episodes = [episode([-1.0, 0.0, 1.0, 2.0]), episode([0.0, 0.0, 4.0, 8.0])]
    # 8 pooled atoms of mass 1/8: CVaR_0.25 is the mean of the top two, (8 + 4) / 2
    m = summarize_calibration(episodes, 0.25, nonnegative=nonnegative)
    assert m["calib/start_tail_cvar"] == pytest.approx(6.0, rel=F64)
    # α = 1: the mean of all atoms, the −1 counted as 0 with nonnegative costs
    m = summarize_calibration(episodes, 1.0, nonnegative=nonnegative)
    expected = (15.0 if nonnegative else 14.0) / 8
    assert m["calib/start_tail_cvar"] == pytest.approx(expected, rel=F64)
    start_std = (np.std([-1.0, 0.0, 1.0, 2.0]) + np.std([0.0, 0.0, 4.0, 8.0])) / 2
    assert m["calib/start_std"] == pytest.approx(start_std, rel=F64)


def test_undefined_metrics_are_nan():
    # no variance head: the std columns are NaN, the rest is unchanged
    with_variance = calibration_metrics([_episode(*e) for e in EPISODES], StubLoss())
    without = calibration_metrics([_episode(*e) for e in EPISODES], StubLoss(variance=False))
    for key in CALIBRATION_KEYS:
        if key in ("calib/start_std", "calib/mean_std"):
            assert math.isnan(without[key]), key
        elif key in ("calib/start_tail_cvar", "calib/start_tail_ratio"):
            # the mixture of the start-state means alone: CVaR_0.5 of (0.5, 3, −1, 1)
            tail = (3.0 + 1.0) / 2
            expected = tail if key.endswith("cvar") else tail / 3.0
            assert without[key] == pytest.approx(expected, abs=1e-9), key
        else:
            assert without[key] == with_variance[key], key
    # one cost-free episode: no spread, realised CVaR 0 (no ratio), constant realised
    # cost-to-go (no correlation)
    m = calibration_metrics([_episode([0.5, -0.5], [1.0, 1.0], [0.0, 0.0])], StubLoss())
    for key in ("calib/realised_spread", "calib/start_cvar_ratio", "calib/correlation"):
        assert math.isnan(m[key]), key
    assert m["calib/start_realised_cvar"] == 0.0 and m["calib/negative_share"] == 0.5
    assert all(math.isnan(v) for v in calibration_metrics([], StubLoss()).values())


@pytest.mark.parametrize(
    ("scale", "offset", "expected"),
    [(2.0, 1.0, 1.0), (-3.0, 0.5, -1.0), (0.0, 1.0, math.nan)],
)
def test_correlation_of_affine_predictions_is_plus_or_minus_one(scale, offset, expected):
    # realised cost-to-go with γ_c = 0.5: [1, 0, 0, 8] -> [2, 2, 4, 8], [4] -> [4];
    # a constant Q^c has no correlation
    realised = [[2.0, 2.0, 4.0, 8.0], [4.0]]
    costs = [[1.0, 0.0, 0.0, 8.0], [4.0]]
    episodes = [
        _episode([scale * g + offset for g in gs], [0.0] * len(gs), cs)
        for gs, cs in zip(realised, costs)
    ]
    correlation = calibration_metrics(episodes, StubLoss())["calib/correlation"]
    if math.isnan(expected):
        assert math.isnan(correlation)
    else:
        assert correlation == pytest.approx(expected, abs=F64)


# ---------------------------------------------------------- recording real episodes
@pytest.mark.parametrize("num_workers", [1, 3])
def test_recorded_episodes_are_the_run_episodes_with_their_steps(num_workers):
    keys = ["observation", "action", ("next", "observation"), ("next", "cost")]
    policy = tiny_goal_seeker()

    def env():
        return make_env("tiny", seed=5, num_workers=num_workers, parallel=False)

    plain = run_episodes(env(), policy, 4, max_steps=100)
    recorded = record_episodes(env(), policy, 4, keys, max_steps=100)
    assert [r.result for r in recorded] == plain  # 2 rounds side by side: 3, then 1
    assert sum(r.result.cost for r in recorded) > 0  # the straight path crosses the hazard
    for episode in recorded:
        steps, result = episode.steps, episode.result
        assert steps.batch_size == torch.Size([result.length])
        assert float(steps["next", "cost"].double().sum()) == pytest.approx(result.cost, abs=1e-9)
        # the action is the policy's at the recorded observation, which follows the last
        torch.testing.assert_close(steps["action"], policy(steps.exclude("action"))["action"])
        torch.testing.assert_close(steps["observation"][1:], steps["next", "observation"][:-1])


def test_calibration_keys_and_support_follow_the_loss():
    from torchrl.data import Bounded
    from torchrl.objectives import SACLoss

    from wcsac_rl import SACLagLoss, WCSACLoss
    from wcsac_rl.modules import make_actor, make_qvalue, make_safety_critic
    from wcsac_rl.objectives import PAPER_OPTIONS

    def parts():
        return make_actor(6, Bounded(-1.0, 1.0, shape=(2,))), [make_qvalue(6, 2) for _ in range(2)]

    wcsac = WCSACLoss(*parts(), make_safety_critic(6, 2), **flat_parts(**PAPER_OPTIONS))
    sac_lag = SACLagLoss(
        *parts(), make_safety_critic(6, 2, variance=False), **flat_parts(**PAPER_OPTIONS)
    )
    assert supports_calibration(wcsac) and supports_calibration(sac_lag)
    assert not supports_calibration(SACLoss(*parts()))
    assert not supports_calibration(None)
    assert calibration_keys(wcsac) == ["observation", "action", ("next", "cost")]
    wcsac.set_keys(cost="my_cost")
    assert calibration_keys(wcsac)[-1] == ("next", "my_cost")

    # compare_episodes splits one batched critic call back into the episodes
    recorded = record_episodes(
        make_env("tiny", seed=1, num_workers=2, parallel=False),
        tiny_goal_seeker(),
        3,
        calibration_keys(sac_lag),
        max_steps=100,
    )
    compared = compare_episodes(recorded, sac_lag)
    for episode, calib in zip(recorded, compared):
        alone = sac_lag.safety_estimates(episode.steps)
        assert calib.cost_value.shape == (episode.result.length,)
        # the same network on a larger batch: equal up to float32 rounding (torch's
        # float32 tolerances; a batched matmul may round a last bit differently)
        torch.testing.assert_close(torch.from_numpy(calib.cost_value).float(), alone["cost_value"])
        np.testing.assert_array_equal(calib.cvar, calib.cost_value)  # α = 1: Γ = Q^c
        assert np.isnan(calib.std).all()
        gamma = sac_lag.cost_gamma
        np.testing.assert_allclose(
            calib.cost_to_go[:-1], calib.cost[:-1] + gamma * calib.cost_to_go[1:], rtol=F64
        )


# ------------------------------------------------------------------ training runs
def _train(run_dir: Path, *overrides: str) -> Path:
    trainer = make_trainer(compose_config("env=tiny", "eval_episodes=3", *overrides), run_dir)
    try:
        return trainer.run()
    finally:
        trainer.close()


def _rows(run_dir: Path) -> list[dict[str, str]]:
    with (run_dir / "progress.csv").open(newline="") as f:
        return list(csv.DictReader(f))


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, Path]:
    """A WCSAC and a SAC run on the tiny env (2 epochs, 3 test episodes each)."""
    root = tmp_path_factory.mktemp("calibration_runs")
    return {algo: _train(root / algo, f"algo={algo}") for algo in ("wcsac", "sac")}


def test_each_epoch_logs_calibration_of_its_test_episodes(runs):
    rows = _rows(runs["wcsac"])
    assert len(rows) == 2
    for row in rows:
        assert set(CALIBRATION_KEYS) | {"loss/constraint_slack"} <= set(row)
        values = {key: float(row[key]) for key in CALIBRATION_KEYS}
        for key in ("start_cost_value", "start_cvar", "start_std", "mean_cost_value"):
            assert math.isfinite(values[f"calib/{key}"]), key
        # the calibration saw the epoch's test episodes
        assert values["calib/episode_cost"] == pytest.approx(
            float(row["eval/episode_cost"]), abs=1e-9
        )
        # Γ = Q^c + (positive multiple of) √V^c at α = 0.5
        assert values["calib/start_cvar"] > values["calib/start_cost_value"]
    # updates start in epoch 1, so both epochs have loss means; the slack is theirs
    for row in rows:
        # (what κ held under the threshold: with kappa_signal=max, the default, the
        # larger of the critic's Γ and the episodes' cost)
        held = row.get("loss/constraint_cvar") or row["loss/cvar"]
        slack = float(row["loss/cost_threshold"]) - float(held)
        assert float(row["loss/constraint_slack"]) == pytest.approx(slack, rel=F64, abs=F64)
    # its curves: the four usual panels, κ, β and the two calibration ones, in a grid of
    # 4 × 2 panels of 4 × 3.6 inches at 100 dpi
    curves = plot_run_curves(runs["wcsac"] / "progress.csv", runs["wcsac"] / "curves.png")
    assert png_size(curves) == (4 * 400, 2 * 360)


def test_calibration_changes_neither_the_episodes_nor_the_training(runs, tmp_path, monkeypatch):
    monkeypatch.setattr(rollout_calibration, "supports_calibration", lambda loss: False)
    plain = _rows(_train(tmp_path / "plain", "algo=wcsac"))
    calibrated = _rows(runs["wcsac"])
    for got, want in zip(plain, calibrated):
        assert not any(key.startswith("calib/") for key in got)
        for key, value in got.items():
            if not key.startswith(("time", "calib/")):
                assert value == want[key], key


def test_runs_without_a_safety_critic_have_no_calibration_columns(runs):
    columns = set(_rows(runs["sac"])[0])
    assert not any(c.startswith("calib/") for c in columns)
    assert "loss/constraint_slack" not in columns
    curves = plot_run_curves(runs["sac"] / "progress.csv", runs["sac"] / "curves.png")
    # return, cost, cost rate, cumulative cost, β: a 4 × 2 grid
    assert png_size(curves) == (4 * 400, 2 * 360)


def test_curves_figure_gets_calibration_and_slack_panels_only_when_logged():
    base = {"frames": [400.0, 800.0], "train/episode_return": [0.1, 0.2]}
    calib = {key: [1.0, 2.0] for key in CALIBRATION_KEYS}
    nan = {"calib/start_cvar": [math.nan, math.nan], "loss/constraint_slack": [math.nan] * 2}
    titles = {
        name: [ax.get_title() for ax in run_curves_figure(columns).axes]
        for name, columns in {
            "plain": base,
            "all-nan": {**base, **nan},
            "calibrated": {**base, **calib, "loss/constraint_slack": [0.5, -0.5]},
        }.items()
    }
    usual = ["episode return", "episode cost", "cost rate"]
    assert titles["plain"] == titles["all-nan"] == usual
    assert titles["calibrated"] == [*usual, CALIBRATION_PANEL, SLACK_PANEL]
    fig = run_curves_figure({**base, **calib, "loss/constraint_slack": [0.5, -0.5]})
    calibration_axes = fig.axes[3]  # (no cost columns: no cumulative-cost panel)
    assert [line.get_ydata().tolist() for line in calibration_axes.get_lines()] == [[1.0, 2.0]] * 4


# ------------------------------------------------------------------------------ CLI
def test_cli_writes_calibration_json_and_refuses_to_overwrite(runs, tmp_path, capsys):
    from wcsac_rl.evaluation.evaluator import evaluate_run

    run = shutil.copytree(runs["wcsac"], tmp_path / "run")
    args = [str(run), "--episodes", "4", "--no-progress"]
    assert calibration_main(args) == 0
    out = capsys.readouterr().out
    assert "Γ_α / CVaR_α (α = 0.5)" in out and f"wrote {run / 'calibration.json'}" in out
    assert "training episodes, read when collected" in out
    written = (run / "calibration.json").read_text()
    data = json.loads(written)
    assert data["algo"] == "wcsac" and data["episodes"] == 4
    # the recipe's critic (conf/algo/wcsac.yaml): quantiles, no variance network
    assert data["safety_critic"] == "iqn" and data["has_variance"] is False
    assert set(data["metrics"]) == {k.removeprefix("calib/") for k in CALIBRATION_KEYS}
    # per epoch, the critic's reading of its training episodes (progress.csv's train_calib/*)
    assert [e["frames"] for e in data["training_episodes"]] == [400, 800]
    progress = _rows(run)
    for epoch, row in zip(data["training_episodes"], progress):
        assert epoch["episodes"] == float(row["train_calib/episodes"]) >= 1
        assert epoch["start_cvar"] == pytest.approx(float(row["train_calib/start_cvar"]), rel=F64)
    assert data["metrics"]["start_cvar_ratio"] is None or data["metrics"]["start_cvar_ratio"] > 0
    episodes = data["per_episode"]
    assert data["metrics"]["episode_cost"] == pytest.approx(
        sum(e["cost"] for e in episodes) / 4, abs=1e-9
    )
    # the first 4 episodes of `python -m wcsac_rl.evaluate` (same seeds)
    evaluation = evaluate_run(run, episodes=4, progress=False)
    for mine, theirs in zip(episodes, evaluation.episodes):
        assert (mine["return"], mine["cost"], mine["length"]) == (
            theirs.ret,
            theirs.cost,
            theirs.length,
        )

    assert calibration_main(args) == 1  # exists: refused, file untouched
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and "--force" in err[0]
    assert (run / "calibration.json").read_text() == written
    assert calibration_main([*args, "--episodes", "2", "--force"]) == 0
    assert json.loads((run / "calibration.json").read_text())["episodes"] == 2


def test_cli_errors_are_one_line_and_exit_code_1(runs, tmp_path, capsys):
    corrupt = shutil.copytree(runs["wcsac"], tmp_path / "corrupt")
    (corrupt / "checkpoints" / "last.pt").write_bytes(b"not a checkpoint")
    cases = {
        tmp_path / "nowhere": "no such",
        tmp_path: "holds no checkpoint",
        runs["sac"]: "has no safety critic",
        corrupt: "cannot read checkpoint",
    }
    for path, message in cases.items():
        assert calibration_main([str(path), "--no-progress"]) == 1, path
        captured = capsys.readouterr()
        err = captured.err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("error: ") and message in err[0], err
        assert not (Path(path) / "calibration.json").exists()
    # the module runs as a script too, with the same exit code
    script = subprocess.run(
        [sys.executable, "-m", "wcsac_rl.calibration", str(runs["sac"])],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert script.returncode == 1 and "has no safety critic" in script.stderr
