"""On-policy learning for CPO: one CPO policy step and a value regression per collector batch.

Each collector batch is used once and dropped (no replay buffer, no random warm-up):
reward and cost GAE, one CPO step of the actor, then ``algo.value_iters`` Adam steps on
``V^r`` and ``V^c`` (docs/reproduce.md, "CPO, the on-policy baseline").
:class:`CPOLearner` does these with any collector; :class:`OnPolicyTrainer` is the run
around it. ``updates`` counts CPO steps; ``time/update_s`` splits into
``time/advantage_s``, ``time/policy_step_s`` and ``time/value_update_s``.
"""

from __future__ import annotations

from typing import Any

import torch
from omegaconf import DictConfig
from tensordict import TensorDictBase
from torchrl import timeit
from torchrl.envs import EnvBase
from torchrl.modules import ProbabilisticActor, ValueOperator

from wcsac_rl.modules.gaussian_actor import make_gaussian_actor, make_state_value
from wcsac_rl.objectives.cpo import CPOLoss
from wcsac_rl.training import builders
from wcsac_rl.training.checkpoint import load_module_state, load_optimizer_state
from wcsac_rl.training.devices import run_devices
from wcsac_rl.training.trainer import Trainer, env_max_episode_steps

__all__ = ["CPOLearner", "OnPolicyTrainer", "make_cpo_loss", "make_cpo_networks"]


def make_cpo_networks(
    cfg: DictConfig, env: EnvBase
) -> tuple[ProbabilisticActor, ValueOperator, ValueOperator]:
    """The Gaussian actor, ``V^r`` and ``V^c`` of ``cfg.algo.network`` for ``env``'s specs."""
    shape = builders.network_shape(cfg)
    obs_dim = env.observation_spec["observation"].shape[-1]
    actor = make_gaussian_actor(
        obs_dim,
        env.action_spec_unbatched,
        log_std_init=float(cfg.algo.network.log_std_init),
        **shape,
    )
    value = make_state_value(obs_dim, out_key="state_value", **shape)
    cost_value = make_state_value(obs_dim, out_key="state_cost_value", **shape)
    device = run_devices(cfg).learner
    return actor.to(device), value.to(device), cost_value.to(device)


def make_cpo_loss(
    cfg: DictConfig,
    actor: ProbabilisticActor,
    value: ValueOperator,
    cost_value: ValueOperator,
    max_episode_steps: int,
) -> CPOLoss:
    """:class:`~wcsac_rl.objectives.cpo.CPOLoss` and its two GAE from ``cfg.algo``."""
    algo = cfg.algo
    loss = CPOLoss(
        actor,
        value,
        cost_value,
        cost_limit=float(cfg.cost_limit),
        max_episode_steps=int(max_episode_steps),
        max_kl=float(algo.max_kl),
        damping=float(algo.damping),
        cg_iters=int(algo.cg_iters),
        backtrack_iters=int(algo.backtrack_iters),
        backtrack_coeff=float(algo.backtrack_coeff),
        entropy_coeff=float(algo.entropy_coeff),
        normalize_advantage=bool(algo.normalize_advantage),
        center_cost_advantage=bool(algo.center_cost_advantage),
    )
    loss.make_value_estimator(
        gamma=float(algo.gamma),
        lmbda=float(algo.lmbda),
        cost_gamma=float(algo.cost_gamma),
        cost_lmbda=float(algo.cost_lmbda),
    )
    return loss


class CPOLearner:
    """CPO's learning from one on-policy batch: GAE, one CPO step, the value regression.

    Holds no env: usable with any TorchRL collector (``OnPolicyTrainer`` wraps it).

    Args:
        loss: the :class:`~wcsac_rl.objectives.cpo.CPOLoss` (its networks are updated).
        value_optimizer: optimizer of ``V^r`` and ``V^c``'s parameters.

    Keyword Args:
        value_iters: optimizer steps per batch (safety-starter-agents: 80).
        value_batch_size: samples per value step; ``None`` = the whole batch.
    """

    VALUE_KEYS = ("loss_value", "loss_cost_value")

    def __init__(
        self,
        loss: CPOLoss,
        value_optimizer: torch.optim.Optimizer,
        *,
        value_iters: int = 80,
        value_batch_size: int | None = None,
    ) -> None:
        if int(value_iters) < 1:
            raise ValueError(f"value_iters must be >= 1, got {value_iters}")
        if value_batch_size is not None and int(value_batch_size) < 1:
            raise ValueError(f"value_batch_size must be >= 1 or None, got {value_batch_size}")
        self.loss = loss
        self.value_optimizer = value_optimizer
        self.value_iters = int(value_iters)
        self.value_batch_size = None if value_batch_size is None else int(value_batch_size)

    @property
    def out_keys(self) -> list[str]:
        """Keys of :meth:`learn`'s output: the CPO step's diagnostics and the value losses."""
        return [*CPOLoss.STEP_KEYS, *self.VALUE_KEYS]

    def learn(self, batch: TensorDictBase) -> TensorDictBase:
        """Learn from one time-ordered ``[*B, T]`` batch; returns the scalars of :attr:`out_keys`."""
        with timeit("advantage"):
            self.loss.compute_advantages(batch)
        flat = batch.reshape(-1)
        with timeit("policy_step"):
            out = self.loss.policy_step(flat)
        with timeit("value_update"):
            loss_value, loss_cost_value = self.update_values(flat)
        out.set("loss_value", loss_value)
        out.set("loss_cost_value", loss_cost_value)
        return out

    def update_values(self, batch: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
        """``value_iters`` optimizer steps on ``V^r`` and ``V^c``; returns the losses before them."""
        with torch.no_grad():
            before = self.loss.value_loss(batch)
        size = batch.numel()
        minibatch = size if self.value_batch_size is None else min(size, self.value_batch_size)
        order, cursor = torch.randperm(size), 0
        for _ in range(self.value_iters):
            if minibatch == size:
                sample = batch
            else:
                if cursor + minibatch > size:
                    order, cursor = torch.randperm(size), 0
                sample = batch[order[cursor : cursor + minibatch]]
                cursor += minibatch
            loss_value, loss_cost_value = self.loss.value_loss(sample)
            (loss_value + loss_cost_value).backward()
            self.value_optimizer.step()
            self.value_optimizer.zero_grad(set_to_none=True)
        return before[0].detach(), before[1].detach()

    def state_dict(self) -> dict[str, Any]:
        """Networks (the loss's state) and the value optimizer."""
        return {
            "loss": self.loss.state_dict(),
            "value_optimizer": self.value_optimizer.state_dict(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`."""
        load_module_state(self.loss, state.get("loss"))
        load_optimizer_state(self.value_optimizer, state["value_optimizer"])


class OnPolicyTrainer(Trainer):
    """:class:`~wcsac_rl.training.trainer.Trainer` for CPO: GAE, a CPO step, value regression."""

    def _build_learner(self) -> None:
        cfg = self.cfg
        self.actor, self.value, self.cost_value = make_cpo_networks(cfg, self.env)
        self.loss = make_cpo_loss(
            cfg, self.actor, self.value, self.cost_value, self.max_episode_steps
        )
        value_optimizer = torch.optim.Adam(
            [*self.value.parameters(), *self.cost_value.parameters()], lr=float(cfg.algo.value_lr)
        )
        self.learner = CPOLearner(
            self.loss,
            value_optimizer,
            value_iters=int(cfg.algo.value_iters),
            value_batch_size=cfg.algo.value_batch_size,
        )
        self.policy = self.actor
        self.init_random_frames = 0  # on-policy: every frame comes from the current policy

    @property
    def loss_keys(self) -> list[str]:
        return self.learner.out_keys

    def learn(self, batch: TensorDictBase) -> list[TensorDictBase]:
        with timeit("update"):  # the whole update, comparable with the off-policy runs
            out = self.learner.learn(batch)
        self.updates += 1
        return [out]

    @classmethod
    def restore_policy(cls, cfg, learner_state, env):
        actor, value, cost_value = make_cpo_networks(cfg, env)
        loss = make_cpo_loss(cfg, actor, value, cost_value, env_max_episode_steps(cfg))
        load_module_state(loss, learner_state.get("loss"))  # the actor shares these parameters
        return actor

    # ---------------------------------------------------------- checkpoint
    def learner_state(self) -> dict[str, Any]:
        return self.learner.state_dict()

    def load_learner_state(self, state: dict[str, Any]) -> None:
        self.learner.load_state_dict(state)
