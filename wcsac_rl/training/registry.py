"""Which trainer trains which algorithm: the one place that knows every trainer.

``conf/algo/<name>.yaml`` chooses the algorithm; :data:`TRAINERS` maps its name to the
:class:`~wcsac_rl.training.trainer.Trainer` subclass that runs it. The base trainer
knows none of its subclasses (they import it, not the other way round), and the
config's validation (:mod:`wcsac_rl.training.config`) names the same algorithms.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from types import MappingProxyType

from omegaconf import DictConfig

from wcsac_rl.training.config import ALGOS, ConfigError
from wcsac_rl.training.off_policy import OffPolicyTrainer
from wcsac_rl.training.on_policy import OnPolicyTrainer
from wcsac_rl.training.trainer import RandomPolicyTrainer, Trainer

__all__ = ["TRAINERS", "make_trainer", "trainer_class"]

TRAINERS = MappingProxyType(
    {
        "wcsac": OffPolicyTrainer,
        "sac_lag": OffPolicyTrainer,
        "cal": OffPolicyTrainer,
        "sac": OffPolicyTrainer,
        "cpo": OnPolicyTrainer,
        "random": RandomPolicyTrainer,
    }
)
"""``algo.name`` → the trainer class (every name of ``config.ALGOS``)."""
assert set(TRAINERS) == set(ALGOS), "the registry and the config validation disagree"


def trainer_class(algo: str) -> type[Trainer]:
    """The :class:`~wcsac_rl.training.trainer.Trainer` subclass that trains ``algo``."""
    try:
        return TRAINERS[algo]
    except KeyError:
        raise ConfigError(f"unknown algo {algo!r}; choose one of {', '.join(ALGOS)}") from None


def make_trainer(
    cfg: DictConfig, run_dir: str | Path, *, overrides: Sequence[str] | None = None
) -> Trainer:
    """The trainer for ``cfg.algo.name`` (its constructor validates ``cfg`` first);
    ``overrides`` (the command line's) go into the run's ``provenance.json``."""
    return trainer_class(cfg.algo.name)(cfg, run_dir, overrides=overrides)
