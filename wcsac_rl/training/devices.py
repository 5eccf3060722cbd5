"""Where a run's pieces live: the one place that reads ``cfg.device``.

* **env** — the training and test envs step on the CPU (MuJoCo and NumPy) and make
  their tensordicts there;
* **learner** — ``cfg.device``: the networks and their targets, β and κ, the optimizers'
  state, the replay buffer's storage (so every sampled batch), the start-state buffer,
  and the policy. The collector moves each collected batch from the env device to the
  learner (``env_device`` / ``policy_device`` / ``storing_device``); off the CPU, the
  off-policy trainer's collector acts with a CPU copy of the actor, which takes the
  learner's weights after each batch's updates (with a shield, which reads the
  learner's safety critic, it acts on the learner). The test episodes' env casts its
  output to the learner and the policy's actions back (TorchRL's
  ``DeviceCastTransform``).

A checkpoint is always loaded on the CPU and copied into the learner's tensors;
evaluation and calibration rebuild a run on the CPU (:data:`CPU`, :func:`on_cpu`),
whatever device it trained on.
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
