"""The paper variants are PAPER_OPTIONS; the kit's recipes (conf/algo/wcsac.yaml,
sac_lag.yaml and their layout files) set what docs/defaults.md says; a stored run whose
config lacks an option of today's kit is refused, naming the commit that wrote it.

(The config's defaults and the loss's are one definition, SafetyOptions, which each
recipe then changes for the trainer: test_options.py and below.)"""

from __future__ import annotations

from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from wcsac_rl.objectives import PAPER_OPTIONS

CONF = Path(__file__).resolve().parents[1] / "conf"


def _algo(*overrides: str):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose("config", overrides=list(overrides)).algo


@pytest.mark.parametrize("env", ["static", "tiny", "dynamic", "point_goal1", "point_goal2"])
@pytest.mark.parametrize(
    ("variant", "name"), [("wcsac_paper", "wcsac"), ("sac_lag_paper", "sac_lag")]
)
def test_paper_variants_are_the_paper_options_on_every_layout(variant, name, env):
    """The paper variant is its algorithm (``name``) with PAPER_OPTIONS, the paper's
    critic, β₀ and one lr, and κ from log 2 with no floor, on every layout (every key:
    tests/test_config_layout.py)."""
    import math

    paper = _algo(f"algo={variant}", f"env={env}")
    assert paper.name == name
    for key, value in PAPER_OPTIONS.items():
        assert paper[key] == value, key
    assert (paper.safety_critic, paper.alpha_init, paper.actor_lr) == ("gaussian", 1.0, None)
    assert (paper.kappa_init, paper.kappa_min) == (math.log(2.0), 0.0)


def test_paper_variant_builds_the_papers_loss():
    from wcsac_rl.envs import make_env
    from wcsac_rl.training import builders

    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("config", overrides=["algo=wcsac_paper", "env=tiny", "risk_level=0.1"])
    env = make_env("tiny", seed=0)
    try:
        loss = builders.make_loss(cfg, builders.make_agent(cfg, env), 100)
    finally:
        env.close()
    assert loss.kappa_states == "replay" and loss.cost_n_steps == 1
    assert loss.cost_gamma == pytest.approx(float(cfg.algo.gamma))
    # the per-step threshold of a discounted critic, not d itself
    expected = cfg.cost_limit * (1 - cfg.algo.gamma**100) / ((1 - cfg.algo.gamma) * 100)
    assert float(loss.cost_threshold) == pytest.approx(expected, rel=1e-6)
    assert builders.make_postproc(loss) is None


COMMIT = "0123456789abcdef0123456789abcdef01234567"


def _run_of_another_commit(tmp_path):
    """A tiny trained run whose checkpoint's config lacks an option of today's kit (as one
    written before the option existed) and whose provenance.json names ``COMMIT``."""
    import json

    import torch
    from _evaluation_helpers import train_run

    run_dir = train_run(tmp_path / "run", "wcsac", 0)
    path = run_dir / "checkpoints" / "last.pt"
    state = torch.load(path, weights_only=True)
    del state["config"]["algo"]["cost_bootstrap_truncated"]
    torch.save(state, path)
    provenance = run_dir / "provenance.json"
    record = json.loads(provenance.read_text())
    record["code"]["commit"] = COMMIT
    provenance.write_text(json.dumps(record))
    return run_dir


def test_a_run_of_another_commits_kit_is_refused_on_resume_and_evaluate(tmp_path):
    """Nothing fills in an option a stored config lacks: resuming or evaluating it is
    one line naming the commit that wrote it and the command that continues it there,
    and changes nothing in the run."""
    import subprocess
    import sys

    from _training_helpers import tree_digests

    from wcsac_rl.training import ConfigError
    from wcsac_rl.training.restore import load_run

    run_dir = _run_of_another_commit(tmp_path)
    line = (
        f"{run_dir} was written by commit 0123456789ab, and its config lacks "
        "algo.cost_bootstrap_truncated that this kit reads; continue it with that "
        "commit's kit: git worktree add ../wcsac-0123456789ab 0123456789ab "
        '(docs/reproduce.md, "A run of another commit")'
    )
    before = tree_digests(run_dir)
    with pytest.raises(ConfigError) as err:
        load_run(run_dir)
    assert str(err.value) == line
    for command in (
        ["-m", "wcsac_rl.train", f"resume={run_dir}", "total_frames=1200"],
        ["-m", "wcsac_rl.evaluate", str(run_dir), "--episodes", "1", "--no-progress"],
    ):
        result = subprocess.run(
            [sys.executable, *command], cwd=tmp_path, capture_output=True, text=True,
            timeout=300,
        )  # fmt: skip
        assert result.returncode == 1, command
        assert f"error: {line}" in result.stderr.splitlines(), result.stderr
        assert tree_digests(run_dir) == before, command
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]  # nothing else written


ENVS = ["static", "tiny", "dynamic", "point_goal1", "point_goal2", "gymnasium"]


@pytest.mark.parametrize("env", ENVS)
def test_the_authors_kappa_advice_is_the_paper_variants_only(env):
    """The authors' κ advice (lr × 50, damping 10 on the harder layouts, lr × 1 and no
    damping on StaticEnv, the tiny env and your own) is what the paper variants use; the
    kit's recipes have one κ rate on every layout, 0.3 × lr without damping (the PID rule
    on DynamicEnv reads neither)."""
    harder = env not in ("static", "tiny", "gymnasium")
    for variant in ("wcsac_paper", "sac_lag_paper"):
        paper = _algo(f"algo={variant}", f"env={env}")
        assert (paper.kappa_lr_scale, paper.damp_scale) == ((50.0, 10.0) if harder else (1.0, 0.0))
    for name in ("wcsac", "sac_lag"):
        kit = _algo(f"algo={name}", f"env={env}")
        assert (kit.kappa_lr_scale, kit.damp_scale) == (0.3, 0.0)


# What docs/defaults.md states the kit's recipes set over the loss's own defaults
# (SafetyOptions, the paper's) and off_policy.yaml's: the StaticEnv study's safety critic
# and κ (10-step, non-negative, undiscounted targets; κ on the start states' tail), the
# training-safety options on every layout
# (conf/algo/wcsac.yaml, sac_lag.yaml; results/training_safety/), on DynamicEnv the PID
# rule from κ = 0.1, never under it, with no integral term, 50-step cost targets and SAC's
# actor rate (layout/wcsac_dynamic.yaml; results/training_safety_dynamic/), and SAC-Lag's
# own: the mean critic, the IQN one on StaticEnv and DynamicEnv, 0.02 ≤ κ ≤ 0.3 on
# DynamicEnv (layout/sac_lag_static.yaml, sac_lag_dynamic.yaml).
TRAINING_SAFETY = {
    "cost_n_steps": 10,
    "nonnegative_cost": True,
    "cost_gamma": 1.0,
    "kappa_states": "initial",
    "kappa_statistic": "tail",
    "safety_critic": "iqn",
    "kappa_signal": "max",
    "kappa_episode_window": 10,
    "kappa_lr_scale": 0.3,
    "alpha_init": 0.1,
    "actor_lr": 3e-4,
}
DYNAMIC = {
    "kappa_rule": "pid",
    "kappa_min": 0.1,
    "kappa_init": 0.1,
    "pid.ki": 0.0,
    "cost_n_steps": 50,
    "actor_lr": 1e-3,
}
SAC_LAG = {"risk_level": 1.0, "variance": False}  # (and the mean critic: no safety_critic=iqn)
SAC_LAG_LAYOUT = {
    "static": {"safety_critic": "iqn"},
    "dynamic": {
        "safety_critic": "iqn",
        "kappa_min": 0.02,
        "kappa_init": 0.02,
        "pid.max_kappa": 0.3,
    },
}


def _whole(*overrides: str) -> dict:
    from omegaconf import OmegaConf

    from wcsac_rl.training.checkpoint import _leaves

    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("config", overrides=list(overrides))
    return _leaves(OmegaConf.to_container(cfg, resolve=True))


def _documented(algo: str, env: str) -> dict:
    values = dict(TRAINING_SAFETY)
    if algo == "sac_lag":
        del values["safety_critic"]
        values |= SAC_LAG
    if env == "dynamic":
        values |= DYNAMIC
    if algo == "sac_lag":
        values |= SAC_LAG_LAYOUT.get(env, {})
    return values


@pytest.mark.parametrize("env", ENVS)
@pytest.mark.parametrize("algo", ["wcsac", "sac_lag"])
def test_the_kit_recipes_are_what_the_defaults_page_states(algo, env):
    """Over SafetyOptions' and off_policy.yaml's values, ``algo=wcsac`` and ``algo=sac_lag``
    set exactly the options docs/defaults.md lists for them on that layout, and nothing
    else."""
    from omegaconf import OmegaConf

    from wcsac_rl.options import SafetyOptions, config_defaults
    from wcsac_rl.training.checkpoint import _leaves

    off_policy = OmegaConf.to_container(OmegaConf.load(CONF / "algo" / "off_policy.yaml"))
    base = _leaves({**off_policy, **config_defaults(SafetyOptions)})
    overrides = [
        f"algo={algo}",
        f"env={env}",
        *(["env.id=MyTask-v0"] if env == "gymnasium" else []),
    ]
    now = {
        k.removeprefix("algo."): v for k, v in _whole(*overrides).items() if k.startswith("algo.")
    }
    ignored = {"name", "label", "recipe"} | ({"risk_level"} if algo == "wcsac" else set())
    differing = {k: now[k] for k in now if k not in ignored and now[k] != base.get(k)}
    assert differing == _documented(algo, env)


@pytest.mark.parametrize("algo", ["sac", "cpo", "random"])
def test_the_algorithms_without_a_lagrangian_have_no_safety_keys(algo):
    """SAC, CPO and the random policy have no safety keys (SAC: its own entropy weight
    and learning rates, off_policy.yaml's)."""
    kit = _whole(f"algo={algo}")
    assert not any(k.startswith(("algo.kappa", "algo.safety")) for k in kit)
    if algo == "sac":
        assert (kit["algo.alpha_init"], kit["algo.actor_lr"]) == (1.0, None)


@pytest.mark.parametrize(
    ("base", "then"),
    [
        (("algo=wcsac", "env=dynamic", "risk_level=0.5"), ("algo.kappa_rule=gradient",)),
        (("algo=sac_lag", "env=static"), ("algo.safety_critic=gaussian",)),
    ],
    ids=["wcsac-dynamic-gradient-rule", "sac_lag-static-mean-critic"],
)
def test_a_run_made_otherwise_resumes_from_its_own_record(tmp_path, base, then):
    """``resume=auto`` on a run whose configuration differs from today's in a key that
    cannot change on resume is refused in one line that says how it continues
    (``resume=<its directory>``), touching nothing of the run; that command continues it
    with every key of its config as it began."""
    from _training_helpers import compose_config
    from omegaconf import OmegaConf

    from wcsac_rl.training import ConfigError, make_trainer
    from wcsac_rl.training.checkpoint import _leaves, load_checkpoint, resume_config

    run_dir = tmp_path / "run"
    first = make_trainer(compose_config(*base, *then, "resume=auto", "total_frames=400"), run_dir)
    try:
        first.run()
    finally:
        first.close()
    files = {p: p.read_bytes() for p in run_dir.rglob("*") if p.is_file() and p.name != ".lock"}
    with pytest.raises(ConfigError) as err:
        make_trainer(compose_config(*base, "resume=auto"), run_dir).close()
    message = str(err.value)
    assert "\n" not in message
    assert message.endswith(f" (resume={run_dir} continues it with its own recorded configuration)")
    assert {p: p.read_bytes() for p in files} == files
    began = _leaves(load_checkpoint(run_dir / "checkpoints" / "last.pt")["config"])
    overrides = [f"resume={run_dir}", "total_frames=800"]
    resumed = make_trainer(resume_config(compose_config(*base, *overrides), overrides), run_dir)
    try:
        resumed.run()
    finally:
        resumed.close()
    now = _leaves(OmegaConf.to_container(resumed.cfg, resolve=True))
    changed = {k for k in began if k in now and began[k] != now[k]}
    assert changed <= {"resume", "total_frames"}, changed
    rows = (run_dir / "progress.csv").read_text().splitlines()
    assert len(rows) == 1 + 2  # header, the first session's epoch and the resumed one's
