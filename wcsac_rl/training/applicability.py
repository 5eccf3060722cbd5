"""Options that only some algorithms read: given for another one, they get a warning.

``wcsac-train algo=sac risk_level=0.1`` trains SAC, which has no risk level: the run is
what the user asked for minus an option they may believe took effect. Each such
top-level option given on the command line is said in one warning line on stderr (the
run goes on: a sweep ``algo=sac,wcsac risk_level=0.1`` is a sensible command). The
``algo.*`` options need no table: each algorithm's config group has only its own, and
any other key is refused (:mod:`~wcsac_rl.training.config_keys`).
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from types import MappingProxyType

from omegaconf import DictConfig

from wcsac_rl.training.registry import ALGORITHMS, Algorithm

__all__ = ["APPLIES_TO", "inapplicable", "readers", "warn_inapplicable"]

APPLIES_TO: Mapping[str, Callable[[Algorithm], bool]] = MappingProxyType(
    {
        "risk_level": lambda a: a.reads_risk_level,  # a risk-neutral one is α = 1
        "compile": lambda a: a.off_policy,  # the SAC family's update
        "cudagraphs": lambda a: a.off_policy,
        "replay_draw": lambda a: a.off_policy,
        "save_replay_buffer": lambda a: a.off_policy,  # only they keep a replay buffer
    }
)
"""Top-level option → which algorithms read it (a property of their registry entry)."""


def readers(key: str) -> tuple[str, ...]:
    """The algorithms (``algo.name``) that read the top-level option ``key``.

    >>> readers("risk_level")
    ('wcsac',)
    """
    return tuple(name for name, entry in ALGORITHMS.items() if APPLIES_TO[key](entry))


def _given(overrides: Sequence[str]) -> list[str]:
    """The top-level keys the overrides set (``risk_level=0.1``, ``++compile=true``)."""
    keys = []
    for override in overrides:
        key, sep, _ = override.lstrip("+~").partition("=")
        if sep and key in APPLIES_TO and key not in keys:
            keys.append(key)
    return keys


def _row_algorithm(row: str) -> str | None:
    """The algorithm ``conf/row/<row>.yaml`` chooses (``None``: no such file, or none)."""
    import yaml

    from wcsac_rl.config_dir import CONF_DIR

    path = Path(CONF_DIR) / "row" / f"{row}.yaml"
    try:
        defaults = (yaml.safe_load(path.read_text(encoding="utf-8")) or {}).get("defaults", [])
    except (OSError, yaml.YAMLError, AttributeError):
        return None
    for entry in defaults:
        if isinstance(entry, dict) and "override /algo" in entry:
            return str(entry["override /algo"])
    return None


def _row_override(cfg: DictConfig, overrides: Sequence[str]) -> list[str]:
    """A warning when a command names both a row (``+row=wcsac_0.1``) and ``algo=``
    choosing another algorithm than the row's: the command line's wins, silently else."""
    given = dict(o.lstrip("+~").partition("=")[::2] for o in overrides if "=" in o)
    row, algo = given.get("row"), given.get("algo")
    row_algo = _row_algorithm(row) if row and algo else None
    if row_algo is None or row_algo == str(cfg.algo.name):
        return []
    return [
        f"warning: algo={algo} replaces the algorithm of row={row} (algo={row_algo}): this "
        f"run is {cfg.algo.name}, labelled {cfg.algo.get('label', cfg.algo.name)}, with the "
        "row's other settings only where it reads them"
    ]


def inapplicable(cfg: DictConfig, overrides: Sequence[str]) -> list[str]:
    """One warning line per option of ``overrides`` that ``cfg``'s algorithm does not read.

    >>> from omegaconf import OmegaConf
    >>> cfg = OmegaConf.create({"algo": {"name": "sac"}})
    >>> inapplicable(cfg, ["risk_level=0.1", "seed=3"])
    ['warning: risk_level=0.1 does not apply to algo=sac (only algo=wcsac reads it); ignored']
    >>> inapplicable(OmegaConf.create({"algo": {"name": "wcsac"}}), ["risk_level=0.1"])
    []
    """
    algo = str(cfg.algo.name)
    lines = _row_override(cfg, overrides)
    for key in _given(overrides):
        names = readers(key)
        if algo not in names:
            value = next(
                o.lstrip("+~").partition("=")[2]
                for o in overrides
                if o.lstrip("+~").partition("=")[0] == key
            )
            who = " / ".join(f"algo={a}" for a in names)
            verb = "reads" if len(names) == 1 else "read"
            lines.append(
                f"warning: {key}={value} does not apply to algo={algo} (only {who} {verb} it); "
                "ignored"
            )
    return lines


def warn_inapplicable(cfg: DictConfig, overrides: Sequence[str]) -> None:
    """Print :func:`inapplicable`'s lines on stderr."""
    for line in inapplicable(cfg, overrides):
        print(line, file=sys.stderr, flush=True)
