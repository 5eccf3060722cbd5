"""Your own gymnasium env: ``env=gymnasium env.id=<registered id | module:callable>``.

The cost reaches ``("next", "cost")`` from ``info[env.cost_key]`` or from a
safety-gymnasium 6-tuple step, value for value; episode length and specs come from
the env; and every bad input on the command line (an id that does not resolve, a
callable that raises, an env without a cost, a discrete action space) is one line on
stderr, no traceback, and no run directory.
"""

from __future__ import annotations

import csv
import math
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch
from _training_helpers import ROOT

from wcsac_rl.envs import (
    CostKeyError,
    EnvSourceError,
    env_info,
    make_env,
    make_user_gym_env,
)

# Envs a user might write, as a module on the Python path (tmp_path, per test).
USER_MODULE = textwrap.dedent(
    """
    import gymnasium as gym
    import numpy as np


    class Walk(gym.Env):
        '''x moves by the action; the cost of step t is t / 10 (a number to recognise);
        the info key and the step API are chosen by the constructor.'''

        def __init__(self, api=5, key="cost", limit=None, drop_cost_at=None,
                     obs_shape=(3,), discrete=False):
            self.api, self.key, self.limit, self.drop_cost_at = api, key, limit, drop_cost_at
            if limit is not None:  # an env that truncates itself says how long its episodes are
                self.max_episode_steps = limit
            self.obs_shape = obs_shape
            self.action_space = (
                gym.spaces.Discrete(3) if discrete
                else gym.spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)
            )
            self.observation_space = gym.spaces.Box(
                -np.inf, np.inf, shape=obs_shape, dtype=np.float64
            )
            self.t = 0

        def _obs(self):
            return np.full(self.obs_shape, float(self.t), dtype=np.float64)

        def reset(self, *, seed=None, options=None):
            super().reset(seed=seed)
            self.t = 0
            return self._obs(), {}

        def step(self, action):
            self.t += 1
            cost = self.t / 10
            terminated = False
            truncated = self.limit is not None and self.t >= self.limit
            if self.api == 6:
                return self._obs(), 1.0, cost, terminated, truncated, {}
            info = {} if self.t == self.drop_cost_at else {self.key: cost, "other": 0}
            return self._obs(), 1.0, terminated, truncated, info


    def six(**kwargs):
        return Walk(api=6, limit=8, **kwargs)


    def five(**kwargs):
        return gym.wrappers.TimeLimit(Walk(**kwargs), max_episode_steps=8)


    def unlimited():
        return Walk()


    def discrete():
        return gym.wrappers.TimeLimit(Walk(discrete=True), max_episode_steps=8)


    def no_cost():
        return gym.wrappers.TimeLimit(Walk(key="penalty"), max_episode_steps=8)


    def broken():
        raise RuntimeError("the simulator licence is missing")


    if "UserWalk-v0" not in gym.registry:
        gym.register("UserWalk-v0", entry_point=Walk, max_episode_steps=6)
    """
)


@pytest.fixture
def user_module(tmp_path, monkeypatch):
    """``user_envs`` (the envs above) importable, as with PYTHONPATH=<its directory>."""
    (tmp_path / "user_envs.py").write_text(USER_MODULE)
    monkeypatch.syspath_prepend(str(tmp_path))
    sys.modules.pop("user_envs", None)
    yield tmp_path
    sys.modules.pop("user_envs", None)


@pytest.mark.parametrize("env_id", ["user_envs:six", "user_envs:five"])
def test_cost_arrives_in_next_cost_step_for_step(user_module, env_id):
    """Both step APIs: ("next", "cost")[t] is the env's cost of step t + 1 (t + 1) / 10,
    float32 [T, 1]; the 8-step limit ends the episode; episode_cost is the running sum."""
    env = make_env("gymnasium", env_id=env_id, seed=0)
    td = env.rollout(8, break_when_any_done=False)
    expected = torch.arange(1, 9, dtype=torch.float32).unsqueeze(-1) / 10
    cost = td["next", "cost"]
    assert cost.shape == (8, 1) and cost.dtype == torch.float32
    torch.testing.assert_close(cost, expected, rtol=0, atol=0)
    torch.testing.assert_close(td["next", "episode_cost"], expected.cumsum(0), rtol=1e-6, atol=0)
    assert td["next", "truncated"].squeeze(-1).tolist() == [False] * 7 + [True]
    assert td["next", "observation"].dtype == torch.float32


def test_cost_key_names_the_info_entry(user_module):
    """env.cost_key=hazard reads info["hazard"] (env.kwargs reach the callable: key=...);
    without it the same env is refused naming the key it lacks and the keys it has."""
    env = make_env("gymnasium", env_id="user_envs:five", cost_key="hazard", seed=0, key="hazard")
    td = env.rollout(3)
    expected = torch.tensor([[1.0], [2.0], [3.0]]) / 10
    torch.testing.assert_close(td["next", "cost"], expected, rtol=0, atol=0)
    with pytest.raises(CostKeyError, match=r"no 'cost' entry \(info keys: \['hazard', 'other'\]\)"):
        env_info("gymnasium", env_id="user_envs:five", key="hazard")


def test_specs_and_episode_length_come_from_the_env(user_module):
    """A registered id: its registration's 6 steps; a callable: its TimeLimit's 8;
    env.max_episode_steps overrides; observations are flattened to float32."""
    assert env_info("gymnasium", env_id="UserWalk-v0")["max_episode_steps"] == 6
    info = env_info("gymnasium", env_id="user_envs:five")
    assert (info["max_episode_steps"], info["obs_dim"], info["action_dim"]) == (8, 3, 2)
    assert (info["action_low"], info["action_high"]) == (-1.0, 1.0)
    assert (
        env_info("gymnasium", env_id="user_envs:unlimited", max_episode_steps=5)[
            "max_episode_steps"
        ]
        == 5
    )
    # the tighter limit counts: the env's own TimeLimit (8) ends episodes before 20
    assert (
        env_info("gymnasium", env_id="user_envs:five", max_episode_steps=20)["max_episode_steps"]
        == 8
    )
    env = make_env("gymnasium", env_id="user_envs:five", seed=0, obs_shape=(2, 3))
    assert env.observation_spec["observation"].shape == (6,)
    assert env.observation_spec["observation"].dtype == torch.float32
    td = env.rollout(2)
    assert td["next", "observation"][1].tolist() == [2.0] * 6
    batched = make_env("gymnasium", env_id="user_envs:six", seed=0, num_workers=3, parallel=False)
    assert batched.rollout(4)["next", "cost"].shape == (3, 4, 1)


def test_a_step_without_the_cost_is_refused_not_read_as_zero(user_module):
    gym_env = make_user_gym_env("user_envs:five", drop_cost_at=3)
    gym_env.reset(seed=0)
    action = np.zeros(2, dtype=np.float32)
    assert gym_env.step(action)[-1]["cost"] == pytest.approx(0.1)
    gym_env.step(action)
    with pytest.raises(CostKeyError, match=r"no cost at step 3: its info has no 'cost' entry"):
        gym_env.step(action)


def test_no_episode_length_asks_for_one(user_module):
    with pytest.raises(EnvSourceError, match=r"set env.max_episode_steps=<steps>"):
        make_user_gym_env("user_envs:unlimited")


def _train(cwd: Path, pythonpath: Path, *overrides: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), str(pythonpath)])}
    return subprocess.run(
        [sys.executable, "-m", "wcsac_rl.train", "env=gymnasium", *overrides],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )


BAD_INPUTS = [
    ("env.id=NoSuchTask-v0", "env.id=NoSuchTask-v0: NameNotFound: Environment `NoSuchTask`"),
    ("env.id=no_such_module:make", "no module named 'no_such_module' on the Python path"),
    ("env.id=user_envs:missing", "module 'user_envs' has no callable 'missing'"),
    ("env.id=user_envs:broken", "building the env raised RuntimeError: the simulator licence"),
    ("env.id=user_envs:no_cost", "its info has no 'cost' entry (info keys: ['other', 'penalty'])"),
    ("env.id=user_envs:discrete", "has a Discrete action space"),
    ("env.id=null", "env=gymnasium needs env.id=<registered gymnasium id | module:callable>"),
]


@pytest.mark.parametrize(("override", "message"), BAD_INPUTS, ids=[b[0] for b in BAD_INPUTS])
def test_bad_env_input_is_one_line_and_leaves_no_run_directory(tmp_path, override, message):
    (tmp_path / "user_envs.py").write_text(USER_MODULE)
    cwd = tmp_path / "work"
    cwd.mkdir()
    result = _train(cwd, tmp_path, override, "total_frames=200000")
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert result.returncode == 1, result.stderr
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith("error: ") and message in lines[0], lines[0]
    assert "Traceback" not in result.stderr + result.stdout
    assert list(cwd.iterdir()) == []  # no outputs/<date>/<run>, no outputs/ either


def test_the_report_of_a_sweep_of_the_users_env(user_module, tmp_path, capsys):
    """``wcsac-report`` on two evaluated runs of the user's env: exit 0; Figure 5 is skipped
    in one line saying why (nothing to draw the paths on), the rest written; no goals
    column in any table (the env has no goals)."""
    from wcsac_rl.evaluate import main as evaluate_main
    from wcsac_rl.report import main as report_main
    from wcsac_rl.train import compose_config
    from wcsac_rl.training import make_trainer

    sweep = tmp_path / "outputs" / "2026-01-01"
    for seed in (0, 1):
        run = sweep / f"{seed}_wcsac_0.5_gymnasium_seed{seed}"
        overrides = ("env=gymnasium", "env.id=user_envs:five", "risk_level=0.5")
        trainer = make_trainer(compose_config(*overrides, f"seed={seed}", "total_frames=400"), run)
        try:
            trainer.run()
        finally:
            trainer.close()
        assert (
            evaluate_main([str(run), "--episodes", "3", "--no-progress", "--trust-env-code"]) == 0
        )
    capsys.readouterr()
    out = tmp_path / "report"
    assert report_main([str(sweep), "--out", str(out)]) == 0  # (no --trust-env-code needed)
    lines = capsys.readouterr().out.splitlines()
    skipped = [line for line in lines if "Figure 5" in line]
    assert skipped == [
        "warning: Figure 5 (trajectories) skipped: env gymnasium has no layout (hazards, "
        "goal) to draw the paths on; they are drawn for the kit's envs (static, dynamic, "
        "point_goal1, point_goal2, tiny)"
    ]
    assert not list(out.glob("fig5*"))
    names = {p.name for p in out.iterdir()}
    assert {"table1.md", "table1.tex", "fig4_training_curves.pdf", "fig6_evaluation.png"} <= names
    assert {"fig_cost_return.pdf", "run_values.csv", "run_statistics.tex"} <= names
    table = (out / "table1.md").read_text().splitlines()
    assert (
        table[2] == "| Algorithm | EC | C0.9 | C0.5 | C0.1 | ER | over budget | episodes (seeds) |"
    )
    assert "goals" not in "\n".join(table)
    for name in ("table1.csv", "run_values.csv", "run_statistics.csv"):
        header = (out / name).read_text().splitlines()[0].split(",")
        assert not [c for c in header if c.startswith("goals")], name
    for name in ("table1.tex", "run_values.md", "run_statistics.md"):
        assert "goals" not in (out / name).read_text(), name
    # the episode outcomes are the classes that apply without a goal, and no goal rate
    assert {"outcomes.md", "outcomes.csv", "fig_outcomes.png"} <= names
    assert (out / "outcomes.csv").read_text().splitlines()[0] == (
        "label,algorithm,seed,run,cost_free,cost,failure,episodes"
    )
    assert (
        "| cost-free | with cost | numerical failure | episodes | run |"
        in (out / "outcomes.md").read_text()
    )
    with (sweep / "0_wcsac_0.5_gymnasium_seed0" / "progress.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert all(math.isnan(float(row["train/goal_rate"])) for row in rows)
    assert "eval/goal_rate" not in rows[0]


def test_a_goal_hold_on_a_users_env_is_one_clear_error(user_module, tmp_path):
    """κ held until the training episodes reach the goal would never move on an env
    without goals."""
    from wcsac_rl.train import compose_config
    from wcsac_rl.training import ConfigError, make_trainer

    overrides = ("env=gymnasium", "env.id=user_envs:five", "algo.kappa_hold_goal_rate=0.9")
    with pytest.raises(ConfigError, match="reports no goals: κ would never move"):
        make_trainer(compose_config(*overrides), tmp_path / "run")


def test_a_cost_entry_that_is_none_is_named_as_none():  # red-team G6
    """The key is there and its value is None: said so, not "no 'cost' entry"."""
    import gymnasium as gym

    from wcsac_rl.envs.gymnasium_env import CostFromStep

    class NoneCost(gym.Env):
        observation_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)
        action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

        def reset(self, *, seed=None, options=None):
            return np.zeros(1, np.float32), {}

        def step(self, action):
            return np.zeros(1, np.float32), 0.0, False, False, {"cost": None}

    env = CostFromStep(NoneCost(), name="none_cost")
    env.reset(seed=0)
    with pytest.raises(CostKeyError) as err:
        env.step(np.zeros(1, np.float32))
    assert str(err.value) == (
        "env.id=none_cost: the cost at step 1 is None (its info's 'cost' entry); put the "
        "step's cost there as a number"
    )
