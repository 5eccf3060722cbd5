"""One recipe per algorithm: what ``conf/`` composes, where it comes from, and what a run
says about it.

``tests/data/composed_configs.json`` holds every algorithm × env, row × env and
experiment (with each row it sweeps) as it composed before the recipes moved into one
file per algorithm (``tests/_composed_configs.py``, recorded on eb55fde, when a preset
and a κ-advice layer shaped them). Each combination composes the same job config today,
key by key, except for the keys listed below, each for its reason.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys

import pytest
import yaml
from _composed_configs import (
    ALL_ALGOS,
    CONF,
    ENVS,
    FIXTURE,
    combinations,
    compose_leaves,
    env_overrides,
    key,
    leaves,
)
from _training_helpers import ROOT, TINY_CLI

from wcsac_rl.options import PAPER_OPTIONS, SafetyOptions, config_defaults
from wcsac_rl.recipes import algorithm_files, check_recipe, layout_files, recipe_of

RECORDED = json.loads(FIXTURE.read_text())

# The keys allowed to differ from the recording, and why:
NEW_KEYS = {
    # the files that shaped ``algo`` (a run prints it first and keeps it): a new key.
    # (The recording has no ``preset`` key to ignore: the removed preset group wrote no
    # key into the job config, only its choice into Hydra's runtime node.)
    "algo.recipe",
    # whether this command may import the env code a resumed run's files name (the
    # user's word on this call: never read from a run, docs/guarantees.md): a new key.
    "trust_env_code",
    # whether the update is replayed as a CUDA graph (device=cuda only): a new key.
    "cudagraphs",
    # whether a batch's updates draw their replay rows at once: a new key.
    "replay_draw",
}
ADDED_OPTIONS = (
    "ensemble_reading",
    "k_ucb",
    "k_ucb_lr",
    "k_ucb_max",
    "prior_scale",
    "damp_clamp",
    "kappa_hold_goal_rate",
)
# ... and the safety-critic options added after the recording (the ensemble's readings,
# random priors, adaptive pessimism, the clamped damping, κ held until the task is
# learned): present wherever the safety options are, each at SafetyOptions' default,
# which reads the ensemble, damps and moves κ as before they existed.
PAPER_VARIANTS = ("wcsac_paper", "sac_lag_paper")
PAPER_LEAKED = {
    # the kit's recipe leaked into the paper variants: the episode window of κ's
    # realised signal (10, on every layout; read only by kappa_signal max/episodes) and,
    # on DynamicEnv, the kit's PID start, floor and integral gain. They now hold the
    # paper's values (SafetyOptions' defaults, which PAPER_OPTIONS keeps): CHANGELOG.md.
    "algo.kappa_episode_window",
    "algo.kappa_init",
    "algo.kappa_min",
    "algo.pid.ki",
}
PAPER_VARIANCE = {"algo.variance_loss", "algo.variance_target"}
# ... and the variance head's two options, whose schema defaults became the paper's (W2
# on Eq. 8's moment target; CHANGELOG.md): the paper variants train with them, and every
# other recipe shows them where it has no variance head to read them (an IQN critic, or
# the mean critic alone): asserted below.
EARLIER_RECIPE_EXPERIMENTS = ("table1_static_laptop", "table1_dynamic_laptop")
# ... and these two experiments selected the removed earlier recipe: their rows now
# hold, in each algo.* key that changed, what today's recipe of the same row on the same
# env composes (itself held to the recording by this test), and nothing else changes
# (the committed runs they made reproduce from their own config.yaml: their RESULTS.md).


def _paper_variant(overrides: tuple[str, ...]) -> bool:
    return any(o in (f"algo={v}", f"+row={v}") for o in overrides for v in PAPER_VARIANTS)


def _todays_row(overrides: tuple[str, ...]) -> tuple[str, ...]:
    """The row × env combination an earlier-recipe experiment's job now composes."""
    experiment = overrides[0].removeprefix("experiment=")
    env = "dynamic" if experiment == "table1_dynamic_laptop" else "static"
    row = [o for o in overrides if o.startswith("+row=")]
    return (*(row or ["algo=wcsac"]), *env_overrides(env))


def test_the_fixture_records_every_combination():
    assert sorted(RECORDED) == sorted(key(c) for c in combinations())


@pytest.mark.parametrize("overrides", combinations(), ids=key)
def test_each_combination_composes_what_was_recorded(overrides):
    then, now = RECORDED[key(overrides)], compose_leaves(overrides)
    added = {f"algo.{name}" for name in ADDED_OPTIONS} if "algo.num_safety_nets" in then else set()
    assert set(now) - set(then) == NEW_KEYS | added
    defaults = leaves(config_defaults(SafetyOptions))
    assert {k: now[k] for k in added} == {k: defaults[k.removeprefix("algo.")] for k in added}
    assert set(then) - set(now) == set()
    changed = {k for k in then if now[k] != then[k]}
    if overrides[0].removeprefix("experiment=") in EARLIER_RECIPE_EXPERIMENTS:
        today = compose_leaves(_todays_row(overrides))
        assert {k for k in changed if not k.startswith("algo.")} == set()
        assert {k: now[k] for k in changed} == {k: today[k] for k in changed}
    elif _paper_variant(overrides):
        assert changed <= PAPER_LEAKED | PAPER_VARIANCE
        paper = leaves(config_defaults(SafetyOptions))
        for k in changed:
            assert now[k] == paper[k.removeprefix("algo.")], k
    else:
        assert changed <= PAPER_VARIANCE
        _unread_where_changed(now, changed)


def _unread_where_changed(now: dict, changed: set) -> None:
    """The variance head's options changed only where no variance head reads them, and
    to the schema's (the paper's) values."""
    if changed:
        assert now["algo.safety_critic"] == "iqn" or now["algo.variance"] is False
        paper = leaves(config_defaults(SafetyOptions))
        assert {k: now[k] for k in changed} == {k: paper[k.removeprefix("algo.")] for k in changed}


def test_the_evidence_runs_in_progress_compose_as_they_began():
    """``experiment=evidence_static`` with the rows two long sweeps are running: every
    key as recorded (the recipe's name aside)."""
    for row in ("wcsac_0.1", "sac_lag", "sac_lag_d1.5"):
        overrides = ("experiment=evidence_static", f"+row={row}")
        now = compose_leaves(overrides)
        added = {f"algo.{name}" for name in ADDED_OPTIONS}
        then = RECORDED[key(overrides)]
        kept = {k: v for k, v in now.items() if k not in NEW_KEYS | added | PAPER_VARIANCE}
        assert kept == {k: v for k, v in then.items() if k not in PAPER_VARIANCE}
        _unread_where_changed(now, {k for k in PAPER_VARIANCE if now[k] != then[k]})


# ---------------------------------------------------------------- the paper's, everywhere
HARDER = ("dynamic", "point_goal1", "point_goal2")
"""The layouts the authors advised a faster, damped κ on (docs/paper.md)."""
AUTHORS_ADVICE = {"kappa_lr_scale": 50.0, "damp_scale": 10.0}


@pytest.mark.parametrize("env", ENVS)
@pytest.mark.parametrize("variant", PAPER_VARIANTS)
def test_the_paper_variants_are_the_paper_options_on_every_layout(variant, env):
    """Every safety-critic and κ key is SafetyOptions' default with PAPER_OPTIONS over
    it, and the authors' κ advice on the layouts they gave it for; the networks and the
    schedule are off_policy.yaml's (one lr, β from 1): nothing of the kit's recipe."""
    now = compose_leaves((f"algo={variant}", *env_overrides(env)))
    sac_lag = variant == "sac_lag_paper"
    assert all(config_defaults(SafetyOptions)[k] == v for k, v in PAPER_OPTIONS.items())
    expected = {
        **config_defaults(SafetyOptions),
        **(AUTHORS_ADVICE if env in HARDER else {}),
        "risk_level": 1.0 if sac_lag else 0.5,
        **({"variance": False} if sac_lag else {}),
    }
    off_policy = yaml.safe_load((CONF / "algo" / "off_policy.yaml").read_text())
    expected = {f"algo.{k}": v for k, v in leaves({**off_policy, **expected}).items()}
    label = "sac_lag_paper" if sac_lag else "wcsac_paper_0.5"
    expected |= {
        "algo.name": "sac_lag" if sac_lag else "wcsac",
        "algo.label": label,
        "algo.recipe": recipe_of(CONF, variant, env),
    }
    assert {k: v for k, v in now.items() if k.startswith("algo.")} == expected


def test_the_papers_dynamicenv_kappa_starts_at_log_2_with_no_floor():
    """``python train.py algo=wcsac_paper env=dynamic --cfg job`` (the same compose)."""
    import math

    for variant in PAPER_VARIANTS:
        now = compose_leaves((f"algo={variant}", "env=dynamic"))
        assert now["algo.kappa_init"] == math.log(2.0) and now["algo.kappa_min"] == 0.0
        assert now["algo.kappa_rule"] == "gradient" and now["algo.cost_n_steps"] == 1


def test_cfg_job_prints_the_papers_kappa_on_dynamicenv():
    result = subprocess.run(
        [sys.executable, str(ROOT / "train.py"), "algo=wcsac_paper", "env=dynamic", "--cfg", "job"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 0, result.stderr
    algo = yaml.safe_load(result.stdout)["algo"]
    assert (algo["kappa_init"], algo["kappa_min"]) == (0.6931471805599453, 0.0)
    assert (
        algo["recipe"] == "conf/algo/wcsac_paper.yaml + conf/algo/layout/wcsac_paper_dynamic.yaml"
    )


# ---------------------------------------------------------------- recipe files
def test_every_recipe_is_at_most_two_files_and_says_which():
    """algo.recipe names the algorithm's file and, where it has one, its layout file,
    and both exist; a layout file is read by its own algorithm only."""
    layouts = layout_files(CONF)
    assert algorithm_files(CONF) == sorted(ALL_ALGOS)
    for algo in ALL_ALGOS:
        for env in ENVS:
            recipe = compose_leaves((f"algo={algo}", *env_overrides(env)))["algo.recipe"]
            files = recipe.split(" + ")
            assert files[0] == f"conf/algo/{algo}.yaml"
            assert files[1:] == (
                [f"conf/algo/layout/{algo}_{env}.yaml"] if (algo, env) in layouts else []
            )
            assert all((ROOT / f).is_file() for f in files)
    assert sorted(layouts) == sorted(
        [("wcsac", "dynamic"), ("sac_lag", "static"), ("sac_lag", "dynamic")]
        + [(v, e) for v in PAPER_VARIANTS for e in HARDER]
    )


def test_no_preset_or_advice_layer_is_left():
    assert not (CONF / "preset").exists()
    for gone in ("preset", "kappa_advice"):
        assert not (CONF / "algo" / gone).exists()
    assert sorted(p.name for p in (CONF / "algo").iterdir() if p.is_dir()) == ["layout"]


def test_help_lists_only_the_groups_a_user_picks(tmp_path):
    result = subprocess.run(
        [sys.executable, str(ROOT / "train.py"), "--help"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 0, result.stderr
    groups = result.stdout.split("== Configuration groups ==")[1].split("== Config ==")[0]
    lines = [line for line in groups.splitlines() if ": " in line]
    assert [line.split(":")[0] for line in lines] == ["algo", "env", "experiment", "logger", "row"]
    assert lines[0] == f"algo: {', '.join(sorted(ALL_ALGOS))}"
    for internal in ("schema", "preset", "kappa_advice", "layout", "off_policy"):
        assert internal not in groups


# ---------------------------------------------------------------- what a run says
def test_a_run_names_its_recipe_first_and_in_its_config(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    run_dir = tmp_path / "run"
    result = subprocess.run(
        [
            sys.executable,
            str(ROOT / "train.py"),
            *TINY_CLI,
            "algo=sac_lag",
            "env=tiny",
            "total_frames=400",
            "epoch_frames=200",
            "logger=none",
            f"hydra.run.dir={run_dir}",
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert result.returncode == 0, result.stderr
    first = result.stdout.splitlines()[0]
    assert first == "recipe: conf/algo/sac_lag.yaml"
    assert (run_dir / "train.log").read_text().splitlines()[0] == first
    saved = yaml.safe_load((run_dir / "config.yaml").read_text())
    assert saved["algo"]["recipe"] == "conf/algo/sac_lag.yaml"


# ---------------------------------------------------------------- bad input
@pytest.fixture
def conf_copy(tmp_path, monkeypatch):
    """A copy of conf/ that the validator reads (wcsac_rl.config_dir.CONF_DIR)."""
    import wcsac_rl.config_dir

    copy = tmp_path / "conf"
    shutil.copytree(CONF, copy)
    monkeypatch.setattr(wcsac_rl.config_dir, "CONF_DIR", copy)
    return copy


@pytest.mark.parametrize(
    ("name", "message"),
    [
        (
            "wcsca_dynamic.yaml",
            "conf/algo/layout/wcsca_dynamic.yaml is a recipe for no algorithm: 'wcsca_dynamic' "
            "does not start with one of cal, cpo, random, sac, sac_lag, sac_lag_paper, wcsac, "
            "wcsac_paper (a layout recipe is named <algorithm>_<env>.yaml)",
        ),
        (
            "wcsac_dinamic.yaml",
            "conf/algo/layout/wcsac_dinamic.yaml is a recipe for no layout: 'dinamic' is not "
            "an env of conf/env/ (dynamic, gymnasium, point_goal1, point_goal2, static, tiny; "
            "a layout recipe is named <algorithm>_<env>.yaml)",
        ),
        (
            "sac_static.yaml",
            "conf/algo/layout/sac_static.yaml is never read: conf/algo/sac.yaml's defaults do "
            "not list `optional layout: sac_${env}`",
        ),
    ],
    ids=["unknown-algorithm", "unknown-layout", "never-read"],
)
def test_a_layout_recipe_hydra_would_never_read_is_refused_and_leaves_no_run(
    conf_copy, tmp_path, name, message
):
    from wcsac_rl.train import compose_config, run_training
    from wcsac_rl.training import ConfigError

    (conf_copy / "algo" / "layout" / name).write_text("# @package algo\nkappa_min: 0.5\n")
    cfg = compose_config(*TINY_CLI, "total_frames=400", "logger=none")
    with pytest.raises(ConfigError) as err:
        run_training(cfg, tmp_path / "run")
    assert str(err.value) == message
    assert not (tmp_path / "run").exists()


def test_a_recipe_naming_an_unknown_algorithm_or_other_files_is_refused(tmp_path):
    """From the command line: one ``error:`` line, no run directory."""
    run_dir = tmp_path / "run"
    for recipe, message in [
        (
            "conf/algo/wcsac2.yaml",
            "error: algo.recipe must start with the algorithm's file (conf/algo/<one of "
            "cal, cpo, random, sac, sac_lag, sac_lag_paper, wcsac, wcsac_paper>.yaml), got "
            "'conf/algo/wcsac2.yaml'",
        ),
        (
            "conf/algo/wcsac.yaml",
            "error: algo.recipe names the files that shaped algo on env=dynamic: "
            "'conf/algo/wcsac.yaml + conf/algo/layout/wcsac_dynamic.yaml', got "
            "'conf/algo/wcsac.yaml' (it is written by those files, not set by hand)",
        ),
    ]:
        result = subprocess.run(
            [
                sys.executable,
                str(ROOT / "train.py"),
                "env=dynamic",
                f"algo.recipe='{recipe}'",
                f"hydra.run.dir={run_dir}",
            ],
            cwd=tmp_path,
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert result.returncode == 1
        assert result.stderr.strip().splitlines() == [message]
        assert not run_dir.exists()


def test_check_recipe_accepts_what_composes():
    for algo in ALL_ALGOS:
        for env in ENVS:
            check_recipe(CONF, recipe_of(CONF, algo, env), env)


REPRODUCED = ROOT / "results" / "heldout_static" / "runs" / "sac_lag_static_seed100"


def test_a_committed_run_trains_again_from_its_own_record_at_its_commit(tmp_path):
    """docs/reproduce.md, "A run of another commit": a committed run's record is its
    whole configuration, which today's kit refuses in one line naming its commit (its
    options are not all today's), and which that commit's kit trains again with Hydra's
    ``--config-path`` (here at a tiny budget, from the commit's files with this venv)."""
    from omegaconf import OmegaConf

    from wcsac_rl.training import ConfigError
    from wcsac_rl.training.checkpoint import _leaves, check_current

    record = REPRODUCED / "config.yaml"
    commit = json.loads((REPRODUCED / "provenance.json").read_text())["code"]["commit"]
    with pytest.raises(ConfigError, match=f"was written by commit {commit[:12]}, and "):
        check_current(OmegaConf.load(record), record)
    known = subprocess.run(
        ["git", "-C", str(ROOT), "cat-file", "-e", f"{commit}^{{commit}}"], capture_output=True
    )
    if known.returncode != 0:
        pytest.skip(f"not a git checkout holding {commit}")
    kit = tmp_path / "kit"
    kit.mkdir()
    archive = subprocess.run(
        ["git", "-C", str(ROOT), "archive", commit, "wcsac_rl", "conf", "train.py"],
        capture_output=True, check=True,
    )  # fmt: skip
    subprocess.run(["tar", "-x", "-C", str(kit)], input=archive.stdout, check=True)
    budget = [
        "total_frames=800",
        "epoch_frames=400",
        "eval_episodes=1",
        "algo.collector.init_random_frames=400",
        "algo.batch_size=64",
        "progress_bar=false",
        "logger.backend=none",
    ]
    run_dir = tmp_path / "run"
    result = subprocess.run(
        [sys.executable, "train.py", f"--config-path={REPRODUCED}", "--config-name=config",
         "resume=null", *budget, f"hydra.run.dir={run_dir}"],
        cwd=kit, env={**os.environ, "PYTHONPATH": str(kit), "OMP_NUM_THREADS": "1"},
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    ran = yaml.safe_load((run_dir / "config.yaml").read_text())
    saved = yaml.safe_load(record.read_text())
    changed = {"algo.batch_size", "algo.collector.init_random_frames", "resume"}
    changed |= {key.split("=")[0] for key in budget}
    assert {k: v for k, v in _leaves(ran).items() if k not in changed} == {
        k: v for k, v in _leaves(saved).items() if k not in changed
    }
    assert len((run_dir / "progress.csv").read_text().splitlines()) == 3
