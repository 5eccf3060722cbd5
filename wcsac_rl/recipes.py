"""Which files hold an algorithm's training recipe, and the groups a user picks from.

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

from pathlib import Path

import yaml

__all__ = [
    "LAYOUT_DIR",
    "algorithm_files",
    "check_layouts",
    "check_recipe",
    "config_groups",
    "layout_files",
    "recipe_of",
]

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
