"""The algorithms the kit trains: one entry each, the one place that names them.

:data:`ALGORITHMS` holds what the kit reads of an algorithm besides its
``conf/algo/<file>.yaml`` (:class:`Algorithm`); the validation, the builders and the
reports read these properties and never compare an algorithm's name (a new algorithm:
docs/own_algorithm.md). Trainers and losses are named by import path and resolved when
a run is built, so this module imports no trainer and ``wcsac-train --help`` stays light.
"""

from __future__ import annotations

import importlib
import re
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any

from wcsac_rl.training.errors import ConfigError

__all__ = [
    "ALGORITHMS",
    "Algorithm",
    "algorithm",
    "find_algorithm",
    "make_loss",
    "make_trainer",
    "resolve",
    "row_algorithm",
    "trainer_class",
]


@dataclass(frozen=True)
class Algorithm:
    """One algorithm: what the kit reads of it besides ``conf/algo/<file>.yaml``.

    Attributes:
        name: its ``algo.name`` (the config's).
        trainer: import path of the :class:`~wcsac_rl.training.trainer.Trainer`
            subclass that trains it.
        title: its rows' name in reports (``"SAC-Lag"``; a row ``<name>_<variant>`` is
            ``<title>-<variant>``, :func:`~wcsac_rl.evaluation.runs.row_name`).
        loss: import path of ``make_loss(cfg, agent, max_episode_steps) -> LossModule``,
            which the off-policy trainer builds its loss with (``None``: its trainer builds
            its own, or it has none).
        off_policy: it learns from a replay buffer (``algo`` holds ``off_policy.yaml``'s
            networks and schedule; ``compile`` and ``save_replay_buffer`` apply).
        safety_critic: it has a safety critic and a multiplier κ (``algo`` holds
            SafetyOptions; the shield, the calibration and the safety checks apply).
        risk_neutral: (with a safety critic) its risk level is 1, Γ = Q^c: reports bold
            its expected cost; otherwise its α is the run's ``risk_level``.
        learns: it restores a learnt policy from a checkpoint (the random policy does not).
        check: import path of ``check(cfg)`` raising one ConfigError line for a bad value
            of its own options (beyond the shared ones the validation checks), or ``None``.
        paper_rows: its rows of the paper's Table 1 (``algo.label`` values), in order.
    """

    name: str
    trainer: str
    title: str
    loss: str | None = None
    off_policy: bool = False
    safety_critic: bool = False
    risk_neutral: bool = False
    learns: bool = True
    check: str | None = None
    paper_rows: tuple[str, ...] = ()

    @property
    def reads_risk_level(self) -> bool:
        """Whether the run's ``risk_level`` is its α (a safety critic, not risk-neutral)."""
        return self.safety_critic and not self.risk_neutral


_OFF_POLICY = "wcsac_rl.training.off_policy.OffPolicyTrainer"
_KIT_LOSS = "wcsac_rl.training.builders.make_loss"

ALGORITHMS: Mapping[str, Algorithm] = MappingProxyType(
    {
        entry.name: entry
        for entry in (  # in the order of the reports' rows
            Algorithm("sac", _OFF_POLICY, "SAC", loss=_KIT_LOSS, off_policy=True,
                      paper_rows=("sac",)),
            Algorithm("sac_lag", _OFF_POLICY, "SAC-Lag", loss=_KIT_LOSS, off_policy=True,
                      safety_critic=True, risk_neutral=True, paper_rows=("sac_lag",)),
            Algorithm("cal", _OFF_POLICY, "CAL", loss=_KIT_LOSS, off_policy=True,
                      safety_critic=True, risk_neutral=True),
            Algorithm("wcsac", _OFF_POLICY, "WCSAC", loss=_KIT_LOSS, off_policy=True,
                      safety_critic=True, paper_rows=("wcsac_0.9", "wcsac_0.5", "wcsac_0.1")),
            Algorithm("cpo", "wcsac_rl.training.on_policy.OnPolicyTrainer", "CPO",
                      check="wcsac_rl.training.config.check_cpo", paper_rows=("cpo",)),
            Algorithm("random", "wcsac_rl.training.trainer.RandomPolicyTrainer",
                      "Random Policy", learns=False, paper_rows=("random",)),
            # a new algorithm: one more Algorithm(...) here (docs/own_algorithm.md)
        )
    }
)  # fmt: skip
"""``algo.name`` → its :class:`Algorithm`, in the order of the reports' rows."""


def algorithm(name: Any) -> Algorithm:
    """The entry of ``algo.name`` ``name``; an unknown one is one ConfigError line."""
    try:
        return ALGORITHMS[name]
    except (KeyError, TypeError):
        raise ConfigError(
            f"unknown algo {name!r}; choose one of {', '.join(ALGORITHMS)} (a new algorithm "
            "is an entry of ALGORITHMS in wcsac_rl/training/registry.py: docs/own_algorithm.md)"
        ) from None


def find_algorithm(name: Any) -> Algorithm | None:
    """The entry of ``algo.name`` ``name``, or ``None`` (a stored run's unknown name)."""
    return ALGORITHMS.get(name) if isinstance(name, str) else None


def resolve(path: str) -> Any:
    """The object at the import path ``path`` (``"package.module.attribute"``)."""
    module, _, attribute = path.rpartition(".")
    try:
        return getattr(importlib.import_module(module), attribute)
    except (ImportError, AttributeError, ValueError) as err:
        raise ConfigError(
            f"cannot import {path!r} (wcsac_rl/training/registry.py): {err}"
        ) from None


def trainer_class(algo: str):
    """The :class:`~wcsac_rl.training.trainer.Trainer` subclass that trains ``algo``."""
    return resolve(algorithm(algo).trainer)


def make_trainer(cfg, run_dir, *, overrides=None):
    """The trainer for ``cfg.algo.name`` (its constructor validates ``cfg`` first);
    ``overrides`` (the command line's) go into the run's ``provenance.json``."""
    return trainer_class(cfg.algo.name)(cfg, run_dir, overrides=overrides)


def make_loss(cfg, agent, max_episode_steps: int):
    """``cfg.algo.name``'s loss, built by its entry's ``loss`` function."""
    entry = algorithm(cfg.algo.name)
    if entry.loss is None:
        raise ConfigError(f"algo={entry.name} builds no loss of its own here (its entry's loss)")
    return resolve(entry.loss)(cfg, agent, max_episode_steps)


def row_algorithm(label: str) -> Algorithm | None:
    """The entry whose rows ``label`` (an ``algo.label``) belongs to: the longest name
    that is the label or its start before ``_`` (``"sac_lag_d1.5"`` → sac_lag,
    ``"wcsac_iqn_0.1"`` → wcsac); ``None`` for none.

    >>> row_algorithm("sac_lag_paper").name, row_algorithm("sac").name, row_algorithm("x")
    ('sac_lag', 'sac', None)
    """
    found = [
        entry
        for name, entry in ALGORITHMS.items()
        if re.fullmatch(rf"{re.escape(name)}(_.*)?", label, flags=re.S)
    ]
    return max(found, key=lambda entry: len(entry.name), default=None)
