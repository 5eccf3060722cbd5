"""Each algorithm's training recipe as a named object, which files hold it, and the
groups a user picks from.

:func:`recipe_options` is what an algorithm's recipe sets on a layout over
``SafetyOptions``' defaults and ``off_policy.yaml``'s, the same as its config files
compose (a test composes every algorithm × layout and compares them key by key):
``KIT_OPTIONS`` (``kit_options("static")``) is WCSAC's on StaticEnv, what ``train.py
algo=wcsac env=static`` runs and what :class:`~wcsac_rl.objectives.WCSACLoss`'s own
defaults are; ``kit_options("dynamic")`` DynamicEnv's; ``PAPER_OPTIONS``
(:mod:`wcsac_rl.options`) the paper's. A user's own loop builds the loss from one with
:func:`~wcsac_rl.objectives.loss_options.loss_parts` and reads the trainer's keys
(``actor_lr``, ``kappa_lr_scale``, ``kappa_episode_window``) from it.

Each algorithm is one file of ``conf/algo/`` (one that names its algorithm or its row:
``name:`` / ``label:``),
its whole recipe over the option definitions it starts from (``off_policy.yaml``, the
SafetyOptions schema). Where the recipe differs by layout, that difference is one file,
``conf/algo/layout/<algorithm>_<env>.yaml``, which the algorithm's file reads after
itself (``optional layout: <algorithm>_${env}`` in its defaults list); it reaches no
other algorithm. Both files write what they are into ``algo.recipe``
(``conf/algo/wcsac.yaml + conf/algo/layout/wcsac_dynamic.yaml``), which a run prints
first and keeps in its ``config.yaml``.

A layout file Hydra would never read (named for no algorithm, for no env, or for an
algorithm whose file reads no layout file) is refused in one line by :func:`check_layouts`,
and a freshly composed ``algo.recipe`` must name exactly the files that shaped it
(:func:`check_recipe`). This module imports nothing heavy: ``wcsac-train --help``
lists the groups with :func:`config_groups`.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from types import MappingProxyType
from typing import Any

import yaml

from wcsac_rl.options import PAPER_OPTIONS

__all__ = [
    "KIT_OPTIONS",
    "LAYOUTS",
    "LAYOUT_DIR",
    "RECIPE_ALGORITHMS",
    "TRAINER_KEYS",
    "algorithm_files",
    "check_layouts",
    "check_recipe",
    "config_groups",
    "kit_options",
    "layout_files",
    "recipe_of",
    "recipe_options",
]

# ------------------------------------------------------------------ the recipes
TRAINER_KEYS: Mapping[str, Any] = MappingProxyType(
    {"alpha_init": 1.0, "actor_lr": None, "lr": 1.0e-3}
)
"""The keys of ``conf/algo/off_policy.yaml`` a recipe may set besides ``SafetyOptions``'
fields, with that file's values (``alpha_init`` is SACLoss's too)."""

LAYOUTS = ("static", "dynamic", "point_goal1", "point_goal2", "tiny", "gymnasium")
"""The layouts a recipe may differ on: the envs of ``conf/env/``."""

KIT_OPTIONS: Mapping[str, Any] = MappingProxyType(
    {
        "safety_critic": "iqn",
        "kappa_signal": "max",
        "kappa_episode_window": 10,
        "kappa_lr_scale": 0.3,
        "alpha_init": 0.1,
        "actor_lr": 3.0e-4,
    }
)
"""The kit's WCSAC recipe on StaticEnv (``conf/algo/wcsac.yaml``; every layout but
DynamicEnv): the IQN safety critic, κ on the larger of the critic's Γ and the last 10
training episodes' empirical CVaR_α at 0.3 × lr, β from 0.1 and the actor at 3e-4.
Its loss options are :class:`~wcsac_rl.objectives.WCSACLoss`'s defaults; evidence:
docs/defaults.md."""

_DYNAMIC_PID = {"kappa_rule": "pid", "cost_n_steps": 50, "actor_lr": 1.0e-3}
_AUTHORS_KAPPA_ADVICE = {"kappa_lr_scale": 50.0, "damp_scale": 10.0}
_SAC_LAG = {"risk_level": 1.0, "variance": False}
_CAL = {
    "risk_level": 1.0,
    "variance": False,
    "num_safety_nets": 4,
    "ensemble_reading": "ucb",
    "damp_scale": 10.0,
    "damp_clamp": True,
    "kappa_states": "replay",
    "kappa_actions": "replay",
    "kappa_statistic": "mean",
    "kappa_parametrization": "log",
    "kappa_init": 0.6931,
    "cost_gamma": 0.99,
    "cost_n_steps": 1,
    "nonnegative_cost": False,
    "lr": 3.0e-4,
}
_PAPER_LAYOUTS = {
    layout: _AUTHORS_KAPPA_ADVICE for layout in ("dynamic", "point_goal1", "point_goal2")
}
# algorithm -> (its recipe on every layout, what differs on a layout): conf/algo/<algorithm>.yaml
# and conf/algo/layout/<algorithm>_<layout>.yaml, whose comments hold the evidence
_RECIPES: dict[str, tuple[Mapping[str, Any], dict[str, Mapping[str, Any]]]] = {
    "wcsac": (
        KIT_OPTIONS,
        {"dynamic": {**_DYNAMIC_PID, "kappa_init": 0.1, "kappa_min": 0.1, "pid": {"ki": 0.0}}},
    ),
    "wcsac_paper": (PAPER_OPTIONS, _PAPER_LAYOUTS),
    "sac_lag": (
        {**_SAC_LAG, **{k: v for k, v in KIT_OPTIONS.items() if k != "safety_critic"}},
        {
            "static": {"safety_critic": "iqn"},
            "dynamic": {
                **_DYNAMIC_PID,
                "safety_critic": "iqn",
                "kappa_init": 0.02,
                "kappa_min": 0.02,
                "pid": {"ki": 0.0, "max_kappa": 0.3},
            },
        },
    ),
    "sac_lag_paper": ({**PAPER_OPTIONS, **_SAC_LAG}, _PAPER_LAYOUTS),
    "cal": (_CAL, {}),
}
RECIPE_ALGORITHMS = tuple(_RECIPES)
"""The algorithms with a safety critic whose recipes :func:`recipe_options` gives."""


def recipe_options(algorithm: str, layout: str = "static") -> Mapping[str, Any]:
    """What ``algo=<algorithm> env=<layout>`` sets over ``SafetyOptions``' defaults and
    ``off_policy.yaml``'s (a nested ``pid`` mapping: the gains it sets), read-only; a
    WCSAC variant's ``risk_level`` is the run's own (``risk_level=...``), not the
    recipe's. An unknown algorithm or layout: one ``ValueError`` line naming it.

    Example:
        >>> recipe_options("wcsac", "dynamic")["kappa_rule"]
        'pid'
    """
    if algorithm not in _RECIPES:
        raise ValueError(
            f"no recipe for algorithm {algorithm!r}: the algorithms with a safety critic "
            f"are {', '.join(RECIPE_ALGORITHMS)}"
        )
    if layout not in LAYOUTS:
        raise ValueError(f"no layout {layout!r}: the layouts are {', '.join(LAYOUTS)}")
    base, layouts = _RECIPES[algorithm]
    return MappingProxyType({**base, **layouts.get(layout, {})})


def kit_options(layout: str = "static") -> Mapping[str, Any]:
    """The kit's WCSAC recipe on ``layout``: :data:`KIT_OPTIONS` and, on DynamicEnv, the
    PID rule from κ = 0.1 with that floor and no integral term, 50-step cost targets and
    the actor at SAC's rate (``conf/algo/layout/wcsac_dynamic.yaml``, with its evidence).
    ``recipe_options("wcsac", layout)``.

    Example:
        >>> kit_options("static") == KIT_OPTIONS
        True
    """
    return recipe_options("wcsac", layout)


LAYOUT_DIR = "layout"
"""``conf/algo/<this>/``: the per-layout recipe files."""

HIDDEN_GROUPS = ("hydra",)
"""Top-level config directories that are not a user's choice (Hydra's own)."""


def _load(path: Path) -> dict:
    node = yaml.safe_load(path.read_text(encoding="utf-8"))
    return node if isinstance(node, dict) else {}


def algorithm_files(conf_dir: Path) -> list[str]:
    """The stems of the files of ``conf/algo/`` that are an algorithm or a variant of one
    (``name:`` or ``label:`` set): what ``algo=...`` picks (``off_policy.yaml``, shared by
    the SAC family, is not one)."""
    return sorted(
        p.stem for p in (conf_dir / "algo").glob("*.yaml") if {"name", "label"} & set(_load(p))
    )


def _envs(conf_dir: Path) -> list[str]:
    return sorted(p.stem for p in (conf_dir / "env").glob("*.yaml"))


def _reads_layouts(conf_dir: Path, algorithm: str) -> bool:
    """Whether ``conf/algo/<algorithm>.yaml`` lists ``optional layout: <algorithm>_${env}``."""
    entries = _load(conf_dir / "algo" / f"{algorithm}.yaml").get("defaults") or []
    wanted = f"{algorithm}_${{env}}"
    return any(isinstance(e, dict) and e.get(f"optional {LAYOUT_DIR}") == wanted for e in entries)


def _parse(stem: str, algorithms: list[str], envs: list[str]) -> tuple[str | None, str | None]:
    """``(algorithm, env)`` of a layout file's stem; ``(algorithm, None)``: no env after
    the longest algorithm it starts with; ``(None, None)``: it starts with none."""
    starts = [a for a in sorted(algorithms, key=len, reverse=True) if stem.startswith(f"{a}_")]
    for algorithm in starts:
        if stem[len(algorithm) + 1 :] in envs:
            return algorithm, stem[len(algorithm) + 1 :]
    return (starts[0] if starts else None), None


def layout_files(conf_dir: Path) -> dict[tuple[str, str], Path]:
    """``{(algorithm, env): path}`` of every file in ``conf/algo/layout/``; a file Hydra
    would never read raises one ``ValueError`` line naming it (:func:`check_layouts`)."""
    algorithms, envs = algorithm_files(conf_dir), _envs(conf_dir)
    found = {}
    for path in sorted((conf_dir / "algo" / LAYOUT_DIR).glob("*")):
        where = f"{conf_dir.name}/algo/{LAYOUT_DIR}/{path.name}"
        usage = "a layout recipe is named <algorithm>_<env>.yaml"
        if path.suffix != ".yaml":
            raise ValueError(f"{where} is not a layout recipe: {usage}")
        algorithm, env = _parse(path.stem, algorithms, envs)
        if algorithm is None:
            raise ValueError(
                f"{where} is a recipe for no algorithm: {path.stem!r} does not start with "
                f"one of {', '.join(algorithms)} ({usage})"
            )
        if env is None:
            raise ValueError(
                f"{where} is a recipe for no layout: {path.stem[len(algorithm) + 1 :]!r} is "
                f"not an env of {conf_dir.name}/env/ ({', '.join(envs)}; {usage})"
            )
        if not _reads_layouts(conf_dir, algorithm):
            raise ValueError(
                f"{where} is never read: {conf_dir.name}/algo/{algorithm}.yaml's defaults "
                f"do not list `optional {LAYOUT_DIR}: {algorithm}_${{env}}`"
            )
        found[algorithm, env] = path
    return found


def check_layouts(conf_dir: Path) -> None:
    """Raise one ``ValueError`` line if a file of ``conf/algo/layout/`` would never be
    read (see :func:`layout_files`)."""
    layout_files(conf_dir)


def recipe_of(conf_dir: Path, algorithm: str, env: str) -> str:
    """What ``algo.recipe`` says for ``algo=<algorithm> env=<env>``: the algorithm's file,
    ``+`` its layout file where it has one."""
    files = [f"conf/algo/{algorithm}.yaml"]
    if (algorithm, env) in layout_files(conf_dir):
        files.append(f"conf/algo/{LAYOUT_DIR}/{algorithm}_{env}.yaml")
    return " + ".join(files)


def check_recipe(conf_dir: Path, recipe: object, env: object) -> None:
    """A composed ``algo.recipe`` names an algorithm of ``conf/algo/`` and exactly the
    files it composes from on ``env``; else one ``ValueError`` line naming the key."""
    algorithms = algorithm_files(conf_dir)
    first = str(recipe).split(" + ", 1)[0]
    algorithm = first.removeprefix("conf/algo/").removesuffix(".yaml")
    if algorithm not in algorithms or first != f"conf/algo/{algorithm}.yaml":
        raise ValueError(
            f"algo.recipe must start with the algorithm's file (conf/algo/<one of "
            f"{', '.join(algorithms)}>.yaml), got {recipe!r}"
        )
    expected = recipe_of(conf_dir, algorithm, str(env))
    if recipe != expected:
        raise ValueError(
            f"algo.recipe names the files that shaped algo on env={env}: {expected!r}, "
            f"got {recipe!r} (it is written by those files, not set by hand)"
        )


def config_groups(conf_dir: Path) -> str:
    """The groups of ``conf/`` a user picks and their options, one ``group: a, b`` line
    each (``--help``): the algorithms, envs, experiments, loggers and rows; not the
    files the algorithms read themselves (``algo/layout/``, ``off_policy.yaml``, the
    option schema) nor Hydra's own groups."""
    lines = []
    for group in sorted(p for p in conf_dir.iterdir() if p.is_dir()):
        if group.name in HIDDEN_GROUPS:
            continue
        if group.name == "algo":
            options = algorithm_files(conf_dir)
        else:
            options = sorted(p.stem for p in group.glob("*.yaml"))
        if options:
            lines.append(f"{group.name}: {', '.join(options)}")
    return "\n".join(lines)
