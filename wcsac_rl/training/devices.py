"""Where a run's pieces live: the one place that reads ``cfg.device``.

The envs step on the CPU; the learner (networks, targets, β and κ, optimizers, the
replay and start-state buffers, the policy) lives on ``cfg.device``, and the collector
moves each batch there. Off the CPU, the off-policy trainer's collector acts with a CPU
copy of the actor, given the learner's weights after each batch's updates (with a
shield, which reads the learner's safety critic, it acts on the learner); the test
env casts its output to the learner (``DeviceCastTransform``). A checkpoint is always
loaded on the CPU; evaluation and calibration rebuild a run there (:data:`CPU`,
:func:`on_cpu`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from omegaconf import DictConfig

__all__ = ["CPU", "RunDevices", "on_cpu", "run_devices"]


@dataclass(frozen=True)
class RunDevices:
    """The devices of a run (see the module's docstring)."""

    env: torch.device
    learner: torch.device

    @property
    def casts(self) -> bool:
        """Whether data crosses devices between the envs and the learner."""
        return self.env != self.learner


CPU = RunDevices(env=torch.device("cpu"), learner=torch.device("cpu"))


def run_devices(cfg: DictConfig) -> RunDevices:
    """The devices of the run configured by ``cfg`` (``cfg.device`` is the learner's)."""
    return RunDevices(env=torch.device("cpu"), learner=torch.device(str(cfg.device)))


def on_cpu(cfg: DictConfig) -> DictConfig:
    """``cfg`` (a saved run's config) set to rebuild the run on :data:`CPU`: evaluation
    and calibration run there whatever device the run trained on. Changes ``cfg``."""
    cfg.device = str(CPU.learner)
    return cfg
