"""Each algorithm's training recipe as a named object, which files hold it, and the
groups a user picks from.

A recipe is written once, in ``conf/algo/``; :func:`recipe_options` reads it from there
(what an algorithm's files set on a layout over ``SafetyOptions``' defaults and
``off_policy.yaml``'s, merged in their defaults list's order as Hydra composes them; a
test composes every algorithm × layout with Hydra and compares key by key).
``KIT_OPTIONS`` (``kit_options("static")``) is WCSAC's on StaticEnv, what ``train.py
algo=wcsac env=static`` runs; ``kit_options("dynamic")`` DynamicEnv's; ``PAPER_OPTIONS``
(:mod:`wcsac_rl.options`, ``algo=wcsac_paper``) the paper's, which are
:class:`~wcsac_rl.objectives.WCSACLoss`'s own defaults. A user's own loop builds the loss
from one with :func:`~wcsac_rl.objectives.loss_options.loss_parts` and reads the
trainer's keys (``actor_lr``, ``kappa_lr_scale``, ``kappa_episode_window``) from it.

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
(:func:`check_recipe`). This module imports nothing heavy (it reads a few small YAML
files at import): ``wcsac-train --help`` lists the groups with :func:`config_groups`.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from types import MappingProxyType
from typing import Any

import yaml

from wcsac_rl.options import SAFETY_ALGOS

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
_META = ("defaults", "name", "label", "recipe")
"""Keys of an algorithm's file that say what it is, not what it sets."""
_TRAINER = ("alpha_init", "actor_lr", "lr")
_SCHEMA = "/schema/safety_options"


def _conf() -> Path:
    from wcsac_rl.config_dir import CONF_DIR

    return CONF_DIR


def _merge(node: dict, update: Mapping[str, Any]) -> None:
    """Hydra's merge of ``update`` into ``node``: nested mappings key by key."""
    for key, value in update.items():
        if isinstance(value, Mapping) and isinstance(node.get(key), Mapping):
            _merge(node[key], value)
        else:
            node[key] = dict(value) if isinstance(value, Mapping) else value


def _own_keys(path: Path) -> dict[str, Any]:
    """What a recipe file sets: every key but its identity (``_META``) and an
    interpolation (``risk_level: ${risk_level}``: the run's own, not the recipe's)."""
    return {
        k: v
        for k, v in _load(path).items()
        if k not in _META and not (isinstance(v, str) and v.startswith("${"))
    }


def _compose(conf_dir: Path, algorithm: str, layout: str) -> dict[str, Any]:
    """What ``conf/algo/<algorithm>.yaml`` sets on ``layout`` over ``off_policy.yaml`` and
    SafetyOptions' defaults, read in its defaults list's order as Hydra composes it. A
    defaults entry this reader does not know is refused naming the file (the recipe test
    composes every algorithm × layout with Hydra and compares)."""
    path = conf_dir / "algo" / f"{algorithm}.yaml"
    node: dict[str, Any] = {}
    for entry in _load(path).get("defaults") or ["_self_"]:
        if entry in ("off_policy", _SCHEMA):
            continue  # (the baseline the recipe is read against)
        if entry == "_self_":
            _merge(node, _own_keys(path))
        elif isinstance(entry, dict) and f"optional {LAYOUT_DIR}" in entry:
            layout_path = conf_dir / "algo" / LAYOUT_DIR / f"{algorithm}_{layout}.yaml"
            if layout_path.is_file():
                _merge(node, _own_keys(layout_path))
        else:
            raise ValueError(
                f"{conf_dir.name}/algo/{path.name}: the defaults entry {entry!r} is not one "
                f"a recipe is read from (off_policy, {_SCHEMA}, _self_, optional "
                f"{LAYOUT_DIR}: <algorithm>_${{env}})"
            )
    return node


def _frozen(node: Mapping[str, Any]) -> Mapping[str, Any]:
    """``node`` read-only all the way down (a nested mapping a read-only copy too)."""
    return MappingProxyType(
        {k: _frozen(v) if isinstance(v, Mapping) else v for k, v in node.items()}
    )


def _safety_algorithms(conf_dir: Path) -> tuple[str, ...]:
    """The files of ``conf/algo/`` whose algorithm has a safety critic (``name:`` one of
    :data:`~wcsac_rl.options.SAFETY_ALGOS`)."""
    return tuple(
        a
        for a in algorithm_files(conf_dir)
        if _load(conf_dir / "algo" / f"{a}.yaml").get("name") in SAFETY_ALGOS
    )


def recipe_options(algorithm: str, layout: str = "static") -> Mapping[str, Any]:
    """What ``algo=<algorithm> env=<layout>`` sets over ``SafetyOptions``' defaults and
    ``off_policy.yaml``'s, read from its files (``conf/algo/<algorithm>.yaml`` and its
    layout file): read-only all the way down (a nested ``pid`` mapping: the gains it
    sets). A WCSAC variant's ``risk_level`` is the run's own (``risk_level=...``), not the
    recipe's. An unknown algorithm or layout: one ``ValueError`` line naming it.

    Example:
        >>> recipe_options("wcsac", "dynamic")["kappa_rule"]
        'pid'
    """
    conf_dir = _conf()
    if algorithm not in RECIPE_ALGORITHMS:
        raise ValueError(
            f"no recipe for algorithm {algorithm!r}: the algorithms with a safety critic "
            f"are {', '.join(RECIPE_ALGORITHMS)}"
        )
    if layout not in LAYOUTS:
        raise ValueError(f"no layout {layout!r}: the layouts are {', '.join(LAYOUTS)}")
    return _frozen(_compose(conf_dir, algorithm, layout))


def kit_options(layout: str = "static") -> Mapping[str, Any]:
    """The kit's WCSAC recipe on ``layout`` (``conf/algo/wcsac.yaml`` and, on DynamicEnv,
    ``conf/algo/layout/wcsac_dynamic.yaml``, each with its evidence):
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


# ------------------------------------------------------------------ read once, at import
LAYOUTS: tuple[str, ...] = tuple(_envs(_conf()))
"""The layouts a recipe may differ on: the envs of ``conf/env/``."""

RECIPE_ALGORITHMS: tuple[str, ...] = _safety_algorithms(_conf())
"""The algorithms with a safety critic whose recipes :func:`recipe_options` gives."""

TRAINER_KEYS: Mapping[str, Any] = MappingProxyType(
    {k: _load(_conf() / "algo" / "off_policy.yaml")[k] for k in _TRAINER}
)
"""The keys of ``conf/algo/off_policy.yaml`` a recipe may set besides ``SafetyOptions``'
fields, with that file's values (``alpha_init`` is SACLoss's too)."""

KIT_OPTIONS: Mapping[str, Any] = recipe_options("wcsac", "static")
"""The kit's WCSAC recipe on StaticEnv, as ``conf/algo/wcsac.yaml`` writes it (every layout
but DynamicEnv): what ``train.py algo=wcsac env=static`` runs. A user's loop builds its
loss with ``WCSACLoss(..., **loss_parts(KIT_OPTIONS))`` (and an IQN critic); evidence:
docs/defaults.md."""
