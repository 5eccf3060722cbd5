"""CPO end to end: the trainer, train.py, checkpoints and resume, load_run, a learning test."""

from __future__ import annotations

import csv
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from _tolerance import assert_close_f32, f32_tolerance
from _training_helpers import COMMON_COLUMNS as BASE_COLUMNS
from _training_helpers import CONF, ROOT, TINY_CPO, compose_config
from omegaconf import OmegaConf
from tensordict import TensorDict
from torchrl.collectors import Collector
from torchrl.data import Bounded, Composite, Unbounded
from torchrl.envs import Compose, EnvBase, RewardSum, StepCounter, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type

from wcsac_rl.envs import CostSum
from wcsac_rl.evaluation.plots import plot_run_curves
from wcsac_rl.modules.gaussian_actor import make_gaussian_actor, make_state_value
from wcsac_rl.objectives.cpo import CPOLoss
from wcsac_rl.training import ConfigError, make_trainer
from wcsac_rl.training.checkpoint import load_checkpoint
from wcsac_rl.training.on_policy import CPOLearner, OnPolicyTrainer
from wcsac_rl.training.restore import load_run

# 2 envs × 100 steps per batch (one tiny-env episode each), 2 epochs of 2 batches
SMALL_CPO = [*TINY_CPO, "total_frames=800", "logger=csv"]
CPO_COLUMNS = {f"loss/{k}" for k in (*CPOLoss.STEP_KEYS, "loss_value", "loss_cost_value")}
COMMON_COLUMNS = {*BASE_COLUMNS, "time/update_s"}


def _cfg(*overrides: str):
    return compose_config(*SMALL_CPO, *overrides, small=False)


def _rows(run_dir: Path) -> list[dict[str, str]]:
    with (run_dir / "progress.csv").open(newline="") as f:
        return list(csv.DictReader(f))


def _train(tmp_path: Path, *overrides: str, name: str = "run"):
    trainer = make_trainer(_cfg(*overrides), tmp_path / name)
    try:
        run_dir = trainer.run()
    finally:
        trainer.close()
    return trainer, run_dir


def test_cpo_trains_through_the_trainer_and_logs_its_diagnostics(tmp_path):
    trainer, run_dir = _train(tmp_path)
    assert isinstance(trainer, OnPolicyTrainer)
    assert trainer.init_random_frames == 0
    rows = _rows(run_dir)
    assert [int(r["frames"]) for r in rows] == [400, 800]
    assert COMMON_COLUMNS | CPO_COLUMNS <= set(rows[0])
    assert "loss/loss_actor" not in rows[0]
    assert [int(r["updates"]) for r in rows] == [2, 4]  # one CPO step per 200-frame batch
    assert [int(r["train/episodes"]) for r in rows] == [4, 4]
    for row in rows:
        assert float(row["loss/kl"]) <= 0.01 + 1e-6  # within the trust region
        # J_C is the mean cost of the batch's finished episodes, d = 15; both columns
        # are J_C − d and J_C rounded to float32 once (2⁻²⁴ of J_C each), so the
        # difference can be far below its terms
        estimate = float(row["loss/episode_cost_estimate"])
        assert float(row["loss/constraint"]) == pytest.approx(
            estimate - 15.0, abs=f32_tolerance(2, max(abs(estimate), 15.0))
        )
        assert float(row["loss/loss_value"]) >= 0 and float(row["loss/loss_cost_value"]) >= 0
    checkpoint = load_checkpoint(trainer.checkpoint_path)
    assert checkpoint["frames"] == 800 and checkpoint["updates"] == 4
    assert set(checkpoint["learner"]) == {"loss", "value_optimizer"}
    assert list((run_dir / "logs").rglob("*.csv"))
    curves = plot_run_curves(run_dir / "progress.csv", tmp_path / "curves.png")
    assert curves.read_bytes().startswith(b"\x89PNG")


def test_cpo_on_static_env_estimates_the_episode_cost_from_the_cost_rate(tmp_path):
    # 1000-step episodes and 400-frame batches: no episode ends, J_C = cost rate × 1000
    trainer, run_dir = _train(
        tmp_path,
        "env=static",
        "algo.collector.frames_per_batch=400",
        "total_frames=400",
        "epoch_frames=400",
        "eval_episodes=0",
    )
    row = _rows(run_dir)[-1]
    assert int(row["train/episodes"]) == 0 and int(row["updates"]) == 1
    rate = trainer.tracker.total_cost / 400
    # integer cost sums are exact in float32; the mean and the product by 1000 round
    # twice there, twice in float64
    assert float(row["loss/episode_cost_estimate"]) == pytest.approx(
        rate * 1000, abs=f32_tolerance(4, rate * 1000)
    )


def test_resume_continues_the_frame_counter_and_the_optimizer(tmp_path):
    trainer, run_dir = _train(tmp_path)
    before = load_checkpoint(trainer.checkpoint_path)
    resumed, same_dir = _train(tmp_path, "total_frames=1200", f"resume={run_dir}", name="other")
    assert same_dir == run_dir
    assert [int(r["frames"]) for r in _rows(run_dir)] == [400, 800, 1200]
    after = load_checkpoint(resumed.checkpoint_path)
    assert after["frames"] == 1200 and after["updates"] == before["updates"] + 2
    # the value optimizer's step counter continued (5 value steps per batch)
    steps = [s["step"] for s in after["learner"]["value_optimizer"]["state"].values()]
    assert all(float(s) == 6 * 5 for s in steps)
    changed = [
        not torch.equal(value, after["learner"]["loss"][key])
        for key, value in before["learner"]["loss"].items()
        if key.startswith("value_network.")
    ]
    assert any(changed)  # training went on
    # a different network is refused
    with pytest.raises(ConfigError, match=r"algo\.network"):
        make_trainer(_cfg("algo.network.width=8", f"resume={run_dir}"), tmp_path / "x")


def test_load_run_restores_the_trained_policy(tmp_path):
    trainer, run_dir = _train(tmp_path)
    restored = load_run(run_dir)
    assert restored.cfg.algo.name == "cpo" and restored.frames == 800
    obs = TensorDict({"observation": torch.randn(7, 6)}, [7])
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        expected = trainer.actor(obs.clone())["action"]
        got = restored.policy(obs.clone())["action"]
    # the same network on the same input; BLAS may still block a product differently
    # for another memory alignment: the 16-wide layers' sums, relative to the largest action
    assert_close_f32(got, expected, ops=16)
    assert not torch.equal(got, torch.zeros_like(got))
    restored.env.close()


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("algo.max_kl=0", "algo.max_kl must be > 0"),
        ("algo.backtrack_coeff=1.0", "algo.backtrack_coeff must be in (0, 1)"),
        ("algo.value_batch_size=0", "algo.value_batch_size must be an integer > 0"),
        ("algo.cost_lmbda=1.5", "algo.cost_lmbda must be in [0, 1]"),
        ("algo.collector.frames_per_batch=201", "must be a multiple"),
    ],
)
def test_bad_cpo_config_fails_before_any_work(tmp_path, override, message):
    with pytest.raises(ConfigError, match=re.escape(message)):
        make_trainer(_cfg(override), tmp_path / "run")
    assert not (tmp_path / "run").exists()


def test_the_table1_row_and_sweep_include_cpo():
    cfg = compose_config("+row=cpo", "epoch_frames=10000", small=False)
    assert cfg.algo.name == "cpo" and cfg.algo.label == "cpo"
    assert cfg.algo.collector.frames_per_batch == 10000  # one CPO update per epoch
    assert compose_config("+row=cpo", small=False).algo.collector.frames_per_batch == 30000
    sweep = OmegaConf.load(CONF / "experiment" / "table1_static.yaml")
    assert "cpo" in sweep.hydra.sweeper.params["+row"].split(",")


def test_train_py_algo_cpo_runs_as_a_subprocess(tmp_path):
    run_dir = tmp_path / "cli_run"
    overrides = [o for o in SMALL_CPO if not o.startswith(("epoch", "total"))]
    result = subprocess.run(
        [
            sys.executable,
            str(ROOT / "train.py"),
            *overrides,
            "total_frames=400",
            "epoch_frames=200",
            f"hydra.run.dir={run_dir}",
        ],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    assert f"run directory: {run_dir}" in result.stdout
    rows = _rows(run_dir)
    assert [int(r["frames"]) for r in rows] == [200, 400]
    assert all(r["loss/accepted"] in ("0.0", "1.0") for r in rows)
    saved = load_checkpoint(run_dir / "checkpoints" / "last.pt")
    assert saved["config"]["algo"]["name"] == "cpo" and saved["updates"] == 2


# ------------------------------------------------------------------ learning
class HazardLine(EnvBase):
    """A batch of 1-D point masses that start inside a hazard (``x > 1``).

    ``x₀ = 1.3 ± 0.1``, ``x ← x + 0.2·clip(a, −1, 1)``, reward ``clip(a)`` (moving
    right pays), cost 1 per step with ``x > 1`` after the move; observation
    ``[x, t/20]``. With 20-step episodes a reward-greedy policy pays cost 20, a
    random one ~10-20; keeping the cost under a budget of 4 means leaving the
    hazard at once and coming back only at the end.
    """

    def __init__(self, num_envs: int, seed: int = 0) -> None:
        super().__init__(batch_size=torch.Size([num_envs]))
        self.observation_spec = Composite(
            observation=Unbounded(shape=(num_envs, 2)),
            cost=Unbounded(shape=(num_envs, 1)),
            shape=(num_envs,),
        )
        self.action_spec = Bounded(-1.0, 1.0, shape=(num_envs, 1))
        self.reward_spec = Unbounded(shape=(num_envs, 1))
        self.x = torch.zeros(num_envs, 1)
        self.t = torch.zeros(num_envs, 1)
        self.rng = torch.Generator().manual_seed(seed)

    def _set_seed(self, seed):
        self.rng = torch.Generator().manual_seed(int(seed))

    def _out(self, reward, cost):
        done = torch.zeros_like(cost, dtype=torch.bool)
        out = {"observation": torch.cat([self.x, self.t / 20], -1), "cost": cost}
        out |= {"done": done, "terminated": done.clone()}
        if reward is not None:
            out["reward"] = reward
        return TensorDict(out, self.batch_size)

    def _reset(self, tensordict):
        n = self.batch_size[0]
        reset = tensordict.get("_reset", None) if tensordict is not None else None
        mask = torch.ones(n, 1, dtype=torch.bool) if reset is None else reset.reshape(n, 1)
        fresh = 1.3 + 0.1 * (2 * torch.rand(n, 1, generator=self.rng) - 1)
        self.x = torch.where(mask, fresh, self.x)
        self.t = torch.where(mask, torch.zeros_like(self.t), self.t)
        return self._out(None, torch.zeros(n, 1))

    def _step(self, tensordict):
        action = tensordict.get("action").clamp(-1.0, 1.0)
        self.x = self.x + 0.2 * action
        self.t = self.t + 1
        return self._out(action, (self.x > 1.0).float())


def _hazard_line(num_envs: int, seed: int) -> TransformedEnv:
    transforms = Compose(
        StepCounter(max_steps=20),
        RewardSum(in_keys=["reward"], out_keys=["episode_reward"]),
        CostSum(in_keys=["cost"], out_keys=["episode_cost"]),
    )
    env = TransformedEnv(HazardLine(num_envs, seed), transforms)
    env.set_seed(seed)
    return env


@pytest.mark.slow
def test_cpo_lowers_the_cost_to_the_limit_on_a_tiny_task():
    """CPO (the trainer's CPOLearner, default trust region) on HazardLine, d = 4."""
    seed, limit, num_envs, batches = 0, 4.0, 64, 40
    torch.manual_seed(seed)
    env = _hazard_line(num_envs, seed)
    actor = make_gaussian_actor(2, env.action_spec_unbatched, width=32)
    value = make_state_value(2, width=32)
    cost_value = make_state_value(2, out_key="state_cost_value", width=32)
    loss = CPOLoss(actor, value, cost_value, cost_limit=limit, max_episode_steps=20)
    learner = CPOLearner(
        loss, torch.optim.Adam([*value.parameters(), *cost_value.parameters()]), value_iters=40
    )
    frames = num_envs * 20 * 2  # 128 episodes per batch
    collector = Collector(
        env,
        actor,
        frames_per_batch=frames,
        total_frames=frames * batches,
        auto_register_policy_transforms=False,
    )
    collector.set_seed(seed)
    costs, returns, cases = [], [], []
    for batch in collector:
        done = batch["next", "done"].squeeze(-1)
        costs.append(float(batch["next", "episode_cost"].squeeze(-1)[done].mean()))
        returns.append(float(batch["next", "episode_reward"].squeeze(-1)[done].mean()))
        cases.append(int(learner.learn(batch)["optim_case"]))
    collector.shutdown()
    print(f"episode cost per batch: {[round(c, 2) for c in costs]}")
    print(f"episode return per batch: {[round(r, 2) for r in returns]}")
    assert costs[0] > 2 * limit  # the initial policy is far over the budget
    assert cases[0] == 0  # ... so CPO starts with infeasible-recovery steps
    final_cost = sum(costs[-10:]) / 10
    assert final_cost <= 1.1 * limit  # and ends at the limit (CPO hovers around d)
    assert max(costs[-10:]) <= 1.25 * limit
    # it is not just fleeing: once feasible, the reward improves under the constraint
    assert sum(returns[-10:]) / 10 > min(returns) + 2.0
