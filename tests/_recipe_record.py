"""What every recipe composes and computes today, to hold a restructured kit to its
values (not collected: no ``test_`` prefix).

``tests/data/recipe_configs.json``: the job config of every algorithm × env, every row ×
env and every experiment (alone and with each row it sweeps), flattened, as
``train.py <overrides>`` composes it. ``tests/data/recipe_losses.pt``: for every
algorithm with a loss × every layout, the loss ``train.py algo=<a>
env=<e> risk_level=0.1`` builds (networks 32 wide, as the record's only change), fed
as the trainer feeds it (its n-step entries, start states and episode window, from the
trainer's own builders) on a fixed batch of two envs' 12-step episodes: every output
and every parameter gradient of one forward/backward. ``python tests/_recipe_record.py``
writes both; ``tests/test_recipe_record.py`` compares today's with them.
"""

from __future__ import annotations

import functools
import json
import sys
from pathlib import Path

import torch
from _composed_configs import ALL_ALGOS, CONF, _sweep_rows, compose_leaves, env_overrides, key
from _composed_configs import ENVS as CONFIG_ENVS
from _loss_reference import episode_flags, outputs_and_gradients
from hydra import compose, initialize_config_dir
from tensordict import TensorDict

RECORD = Path(__file__).parent / "data" / "recipe_losses.pt"
CONFIG_RECORD = Path(__file__).parent / "data" / "recipe_configs.json"
ALGOS = ("wcsac", "wcsac_paper", "sac_lag", "sac_lag_paper", "cal", "sac")
ENVS = ("static", "dynamic", "point_goal1", "point_goal2", "tiny")
WIDTH = 32


def combos() -> list[tuple[str, str]]:
    """The recipes whose losses are recorded: (algorithm, layout)."""
    return [(algo, env) for algo in ALGOS for env in ENVS]


def config_combos() -> list[tuple[str, ...]]:
    """Every override list whose composed config is recorded."""
    found = [(f"algo={a}", *env_overrides(e)) for a in ALL_ALGOS for e in CONFIG_ENVS]
    rows = sorted(p.stem for p in (CONF / "row").glob("*.yaml"))
    found += [(f"+row={r}", *env_overrides(e)) for r in rows for e in CONFIG_ENVS]
    for path in sorted((CONF / "experiment").glob("*.yaml")):
        found.append((f"experiment={path.stem}",))
        found += [(f"experiment={path.stem}", f"+row={r}") for r in _sweep_rows(path.stem)]
    return found


def _config(algo: str, env: str):
    import wcsac_rl  # noqa: F401  (registers the option schema)

    overrides = [f"algo={algo}", f"env={env}", "risk_level=0.1", f"algo.network.width={WIDTH}"]
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose("config", overrides=overrides)


@functools.cache
def _specs(env: str):
    """The layout's observation size and action spec (one env built per layout)."""
    from wcsac_rl.training import builders

    made = builders.make_eval_env(_config("sac", env), seed=0, num_envs=1)
    try:
        return made.observation_spec["observation"].shape[-1], made.action_spec_unbatched
    finally:
        made.close()


class _Specs:
    """What ``builders.make_agent`` reads of an env."""

    def __init__(self, env: str) -> None:
        obs_dim, self.action_spec_unbatched = _specs(env)
        self.observation_spec = {"observation": torch.zeros(obs_dim)}


def _batch(cfg, loss, obs_dim: int, act_dim: int) -> TensorDict:
    """Two envs' 12-step episodes (costs, a terminal step, a second episode), with what the
    trainer attaches for this loss."""
    from wcsac_rl.training import builders

    g = torch.Generator().manual_seed(1)
    shape = (2, 12)
    terminated, done, step = episode_flags()
    cost = torch.bernoulli(torch.full((*shape, 1), 0.3), generator=g)
    traj = TensorDict(
        {
            "observation": torch.randn(*shape, obs_dim, generator=g),
            "action": torch.rand(*shape, act_dim, generator=g) * 2 - 1,
            "step_count": step.unsqueeze(-1),
            "next": {
                "observation": torch.randn(*shape, obs_dim, generator=g),
                "reward": torch.randn(*shape, 1, generator=g),
                "cost": cost,
                "done": done,
                "terminated": terminated,
                "truncated": done & ~terminated,
                "step_count": (step + 1).unsqueeze(-1),
                "episode_cost": cost.cumsum(1),
            },
        },
        list(shape),
    )
    postproc = builders.make_postproc(loss)
    if postproc is not None:
        traj = postproc(traj)
    batch = traj.reshape(-1)
    if getattr(loss, "kappa_states", "replay") == "initial":
        starts = builders.make_initial_state_buffer(cfg, loss)
        starts.add_starts(traj)
        torch.manual_seed(3)
        batch = starts.attach(batch)
    if getattr(loss, "kappa_signal", "critic") != "critic" or getattr(
        getattr(loss, "safety_head", None), "reads_episode_costs", False
    ):
        window = builders.make_episode_window(cfg, loss)
        window.add_episodes(traj)
        batch = window.attach(batch)
    return batch


def recipe_outputs(algo: str, env: str) -> dict[str, torch.Tensor]:
    """``out/<key>`` for every loss output and ``grad/<parameter>`` after one backward."""
    from wcsac_rl.training import builders, registry

    cfg = _config(algo, env)
    specs = _Specs(env)
    torch.manual_seed(0)
    agent = builders.make_agent(cfg, specs)
    loss = registry.make_loss(cfg, agent, 12)
    obs_dim = specs.observation_spec["observation"].shape[-1]
    batch = _batch(cfg, loss, obs_dim, specs.action_spec_unbatched.shape[-1])
    return outputs_and_gradients(loss, batch)


if __name__ == "__main__":
    RECORD.parent.mkdir(parents=True, exist_ok=True)
    configs = {key(c): compose_leaves(c) for c in config_combos()}
    CONFIG_RECORD.write_text(json.dumps(configs, indent=1, sort_keys=True) + "\n")
    torch.save({f"{a} {e}": recipe_outputs(a, e) for a, e in combos()}, RECORD)
    print(f"wrote {CONFIG_RECORD} ({len(configs)} configs), {RECORD} ({len(combos())} losses)",
          file=sys.stderr)  # fmt: skip
