"""One small factory per piece of a run: envs, networks, loss, optimizers, collector, buffer, logger.

Each takes the Hydra config (``cfg``) and returns a TorchRL object, so ``train.py``
and the trainer read as the data flow: cfg → env → agent → loss → collector →
replay buffer → update → logger.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType
from torchrl.modules import ProbabilisticActor
from torchrl.objectives import LossModule, SACLoss
from torchrl.record.loggers import Logger

from wcsac_rl.modules import (
    CriticShield,
    TanhNormalPolicy,
    make_actor,
    make_qvalue,
    make_safety_critic,
)
from wcsac_rl.objectives import (
    EpisodeCostWindow,
    NStepCost,
    PolyakUpdate,
    SACLagLoss,
    StartStateBuffer,
    WCSACLoss,
    loss_parts,
    param_groups,
)
from wcsac_rl.options import SafetyOptions
from wcsac_rl.training.config import safety_options
from wcsac_rl.training.devices import RunDevices, run_devices
from wcsac_rl.training.registry import algorithm
from wcsac_rl.training.replay import NStepReplayBuffer, nested_key

__all__ = [
    "Agent",
    "adam",
    "env_kwargs",
    "episode_window",
    "make_agent",
    "make_collector",
    "make_episode_window",
    "make_eval_env",
    "make_initial_state_buffer",
    "make_logger",
    "make_loss",
    "make_optimizers",
    "make_postproc",
    "make_replay_buffer",
    "make_target_updater",
    "make_train_env",
    "network_shape",
    "safety_critic_kwargs",
]


def env_kwargs(cfg: DictConfig) -> dict:
    """Keyword arguments for ``make_env`` from ``cfg.env`` (constructor kwargs, episode
    length; for ``env=gymnasium`` also ``env_id`` and ``cost_key``)."""
    extra = cfg.env.get("kwargs")
    kwargs = {} if extra is None else OmegaConf.to_container(extra, resolve=True)
    if cfg.env.get("max_episode_steps") is not None:
        kwargs["max_episode_steps"] = int(cfg.env.max_episode_steps)
    if cfg.env.name == "gymnasium":  # your own env: its id and the info entry of its cost
        kwargs["env_id"] = str(cfg.env.id)
        kwargs["cost_key"] = str(cfg.env.get("cost_key", "cost"))
    return kwargs


def make_train_env(cfg: DictConfig) -> EnvBase:
    """The training envs: ``algo.collector.num_envs`` copies, batched in one TorchRL env."""
    from wcsac_rl.envs import make_env

    collector = cfg.algo.collector
    return make_env(
        cfg.env.name,
        seed=int(cfg.seed),
        num_workers=int(collector.num_envs),
        parallel=collector.get("env_backend", "serial") == "parallel",
        device=run_devices(cfg).env,  # the collector moves the batches to the learner
        **env_kwargs(cfg),
    )


EVAL_SEED_OFFSET = 1_000_003


def make_eval_env(
    cfg: DictConfig,
    *,
    seed: int | None = None,
    num_envs: int = 1,
    devices: RunDevices | None = None,
) -> EnvBase:
    """The env for test episodes, seeded ``seed`` (default: apart from the training
    envs, ``cfg.seed + 1000003``): unbatched, or ``num_envs`` sub-envs stepped side
    by side in this process (seeded ``seed``, ``seed + 1``, ...). It steps on the env
    device and, where the learner is elsewhere, casts its output to the learner and the
    actions back (``DeviceCastTransform``), so the policy reads it where it lives."""
    from torchrl.envs import DeviceCastTransform

    from wcsac_rl.envs import make_env

    devices = devices or run_devices(cfg)
    if seed is None:
        seed = int(cfg.seed) + EVAL_SEED_OFFSET
    env = make_env(
        cfg.env.name,
        seed=int(seed),
        device=devices.env,
        num_workers=int(num_envs),
        parallel=False,
        **env_kwargs(cfg),
    )
    if devices.casts:
        env.append_transform(DeviceCastTransform(devices.learner, orig_device=devices.env))
    return env


@dataclass
class Agent:
    """The networks of a run (the loss holds their functional parameters)."""

    actor: ProbabilisticActor
    qvalues: list[TensorDictModule]
    safety: TensorDictModule | list[TensorDictModule] | None  # (a list: num_safety_nets > 1)


def network_shape(cfg: DictConfig) -> dict[str, Any]:
    """``width``, ``depth`` and ``activation`` of ``cfg.algo.network`` (every MLP's shape)."""
    net = cfg.algo.network
    return {"width": int(net.width), "depth": int(net.depth), "activation": str(net.activation)}


def make_agent(cfg: DictConfig, env: EnvBase, devices: RunDevices | None = None) -> Agent:
    """Actor, twin reward critic and (for WCSAC / SAC-Lag) the safety critic
    (``algo.safety_critic``: Gaussian or IQN), on the learner device."""
    net = cfg.algo.network
    shape = network_shape(cfg)
    action_spec = env.action_spec_unbatched
    obs_dim = env.observation_spec["observation"].shape[-1]
    act_dim = action_spec.shape[-1]
    actor = make_actor(
        obs_dim,
        action_spec,
        log_std_min=float(net.log_std_min),
        log_std_max=float(net.log_std_max),
        **shape,
    )
    qvalues = [make_qvalue(obs_dim, act_dim, **shape) for _ in range(2)]
    safety = None
    if algorithm(cfg.algo.name).safety_critic:
        options = safety_options(cfg.algo)
        kwargs = safety_critic_kwargs(options)
        # one module, or num_safety_nets of them, each initialised on its own
        critics = [
            make_safety_critic(obs_dim, act_dim, **kwargs, **shape)
            for _ in range(options.num_safety_nets)
        ]
        safety = critics[0] if len(critics) == 1 else critics
    device = (devices or run_devices(cfg)).learner
    actor.to(device)
    for module in [*qvalues, *(safety if isinstance(safety, list) else [safety])]:
        if module is not None:
            module.to(device)
    return Agent(actor, qvalues, safety)


def safety_critic_kwargs(options: SafetyOptions) -> dict:
    """``make_safety_critic``'s keywords for ``options`` (its kind and that kind's own)."""
    if options.safety_critic == "iqn":
        return {"kind": "iqn", "num_cosines": options.iqn.num_cosines}
    return {"kind": "gaussian", "variance": options.variance}


def make_loss(cfg: DictConfig, agent: Agent, max_episode_steps: int) -> LossModule:
    """``WCSACLoss`` / ``SACLagLoss`` / TorchRL ``SACLoss`` with the config's hyperparameters."""
    algo = cfg.algo
    common = {
        "loss_function": "l2",
        "alpha_init": float(algo.alpha_init),
        "target_entropy": algo.target_entropy
        if algo.target_entropy == "auto"
        else float(algo.target_entropy),
    }
    entry = algorithm(algo.name)
    if not entry.safety_critic:
        loss = SACLoss(agent.actor, agent.qvalues, num_qvalue_nets=2, **common)
    else:
        cls = SACLagLoss if entry.risk_neutral else WCSACLoss
        # the loss's parts from every option it reads, from the one definition
        # (wcsac_rl/options.py): checked and typed; a stored config lacking one is refused
        options = safety_options(algo)
        if not entry.risk_neutral:  # (SAC-Lag and CAL are α = 1)
            common["risk_level"] = options.risk_level
        loss = cls(
            agent.actor,
            agent.qvalues,
            agent.safety,
            cost_limit=float(cfg.cost_limit),
            max_episode_steps=int(max_episode_steps),
            **{**loss_parts(options), **common},
        )
    # (its γ buffer is made on the default device unless told)
    loss.make_value_estimator(gamma=float(algo.gamma), device=run_devices(cfg).learner)
    return loss


def make_collection_policy(cfg: DictConfig, loss: LossModule, policy: TanhNormalPolicy):
    """The policy the collector acts with: ``policy`` itself, or, with
    ``algo.shield.candidates >= 2`` (WCSAC, SAC-Lag), ``policy`` behind a
    :class:`~wcsac_rl.modules.CriticShield` reading ``loss``'s safety critic, its
    threshold ``algo.shield.scale`` × the loss's ``cost_threshold`` (read at each step)."""
    if not algorithm(cfg.algo.name).safety_critic:
        return policy
    shield = safety_options(cfg.algo).shield
    if not shield.candidates:
        return policy
    scale, threshold = shield.scale, loss.cost_threshold
    return CriticShield(
        policy,
        loss.action_cvar,
        lambda: scale * float(threshold),
        candidates=shield.candidates,
    )


def make_target_updater(cfg: DictConfig, loss: LossModule) -> PolyakUpdate:
    """Polyak averaging of every target network (reward and safety critics)."""
    return PolyakUpdate(loss, tau=float(cfg.algo.tau))


def adam(params, lr: float) -> torch.optim.Adam:
    """Adam, fused where the device supports it (the same update, ~4× faster on one CPU core
    for the paper's networks) and capturable on CUDA (safe to capture in a CUDA graph).
    """
    params = list(params)
    device = params[0].device.type
    return torch.optim.Adam(
        params, lr=lr, fused=device in ("cpu", "cuda", "mps"), capturable=device == "cuda"
    )


def make_optimizers(cfg: DictConfig, loss: LossModule) -> dict[str, torch.optim.Optimizer]:
    """One Adam per parameter group of :func:`~wcsac_rl.objectives.param_groups`: actor,
    critics, entropy weight, safety weight κ.

    κ's learning rate is ``lr × kappa_lr_scale`` (the authors' ``lr_scale``).
    """
    actor_lr = cfg.algo.get("actor_lr")
    groups = param_groups(
        loss,
        float(cfg.algo.lr),
        actor_lr=None if actor_lr is None else float(actor_lr),
        kappa_lr_scale=float(cfg.algo.get("kappa_lr_scale", SafetyOptions.kappa_lr_scale)),
    )
    return {group["name"]: adam(group["params"], group["lr"]) for group in groups}


def make_collector(
    cfg: DictConfig,
    env: EnvBase,
    policy: TensorDictModule | None,
    *,
    total_frames: int,
    init_random_frames: int,
    seed: int,
) -> Collector:
    """TorchRL ``Collector`` over the batched training envs (random actions first), seeded:
    the envs step on the env device, the batches are stored on the learner device, and the
    policy acts on the device its parameters are on (so that TorchRL acts with ``policy``
    itself, never with a copy whose weights nothing updates).
    """
    devices = run_devices(cfg)
    policy_device = devices.learner
    if policy is not None:
        params = next(iter(policy.parameters()), None)
        if params is not None:
            policy_device = params.device
    collector = Collector(
        env,
        policy,
        frames_per_batch=int(cfg.algo.collector.frames_per_batch),
        total_frames=int(total_frames),
        init_random_frames=int(init_random_frames) if policy is not None else None,
        exploration_type=ExplorationType.RANDOM,
        env_device=devices.env,
        policy_device=policy_device,
        storing_device=devices.learner,
        auto_register_policy_transforms=False,  # the MLP policy needs no env transforms
    )
    if policy is not None and collector.policy is not policy:
        raise RuntimeError("the collector copied the policy: it would act with stale weights")
    collector.set_seed(int(seed))
    return collector


def make_replay_buffer(
    cfg: DictConfig, postproc: NStepCost | None = None, stored_keys: Sequence[NestedKey] = ()
) -> TensorDictReplayBuffer:
    """Uniform replay on a ``LazyTensorStorage`` (the paper: 10⁶ transitions, batch 256).

    With n-step cost entries (``postproc``) whose states are among the ``stored_keys``
    under ``"next"`` and collected pieces that fit the buffer, an
    :class:`~wcsac_rl.training.replay.NStepReplayBuffer`, which reads the n-step state
    from the row holding it instead of storing it twice (its ``gathered_keys``)."""
    storage = LazyTensorStorage(int(cfg.algo.buffer_size), device=run_devices(cfg).learner)
    batch_size = int(cfg.algo.batch_size)
    stored = {nested_key(key) for key in stored_keys}
    if (
        postproc is not None
        and int(cfg.algo.collector.frames_per_batch) <= int(cfg.algo.buffer_size)
        and all(nested_key("next", key) in stored for key in postproc.observation_keys)
    ):
        return NStepReplayBuffer(
            storage=storage,
            batch_size=batch_size,
            nstep_key=postproc.out_key,
            state_keys=postproc.observation_keys,
        )
    return TensorDictReplayBuffer(storage=storage, batch_size=batch_size)


def make_postproc(loss: LossModule) -> NStepCost | None:
    """The n-step cost entries the loss reads (``cost_n_steps > 1``), else ``None``."""
    n_steps = getattr(loss, "cost_n_steps", 1)
    if n_steps <= 1:
        return None
    return NStepCost.for_loss(loss)


INITIAL_STATE_CAPACITY = 10_000


def make_initial_state_buffer(cfg: DictConfig, loss: LossModule) -> StartStateBuffer:
    """The start states the κ loss reads (the last 10⁴), for ``kappa_states=initial``."""
    return StartStateBuffer.for_loss(
        loss, capacity=INITIAL_STATE_CAPACITY, device=run_devices(cfg).learner
    )


def make_episode_window(cfg: DictConfig, loss: LossModule) -> EpisodeCostWindow:
    """The recent training episodes whose CVaR κ sees, for ``kappa_signal`` ``max`` /
    ``episodes`` (the last ``algo.kappa_episode_window``), and the last
    ``algo.kappa_test_window`` test episodes (0: none)."""
    return episode_window(safety_options(cfg.algo), loss)


def episode_window(options: SafetyOptions, loss: LossModule) -> EpisodeCostWindow:
    """:func:`make_episode_window` for ``options`` already read from a config."""
    return EpisodeCostWindow.for_loss(
        loss,
        window=options.kappa_episode_window,
        statistic=options.kappa_episode_statistic,
        test_window=options.kappa_test_window,
    )


def make_logger(
    cfg: DictConfig,
    run_dir: Path,
    *,
    state: dict | None = None,
    resume_frames: int | None = None,
) -> Logger | None:
    """A ``torchrl.record.loggers`` logger writing under ``run_dir/logs`` (or ``None``). A
    resumed run passes its checkpoint's logger ``state`` and frames: wandb continues the
    same run, TensorBoard hides the events after the checkpoint (``purge_step``).
    """
    backend = cfg.logger.backend
    log_dir = run_dir / "logs"
    name = str(cfg.run_name)
    if backend == "none":
        return None
    if backend == "csv":
        from torchrl.record.loggers.csv import CSVLogger

        logger = CSVLogger(exp_name=name, log_dir=str(log_dir))
    elif backend == "tensorboard":
        logger = _tensorboard_logger(
            name, log_dir, purge_step=None if resume_frames is None else resume_frames + 1
        )
    elif backend == "wandb":
        from torchrl.record.loggers.wandb import WandbLogger

        mode = cfg.logger.get("mode", "auto")
        if mode == "auto":
            mode = "online" if _wandb_key_available() else "offline"
        log_dir.mkdir(parents=True, exist_ok=True)
        run_id = ((state or {}).get("local") or {}).get("id")
        logger = WandbLogger(
            exp_name=name,
            offline=mode == "offline",
            save_dir=str(log_dir),
            project=str(cfg.logger.project),
            group=str(cfg.logger.group),
            config=OmegaConf.to_container(cfg, resolve=True),
            id=run_id,  # None: a new wandb run; else the resumed run's own
        )
    else:
        raise ValueError(f"unknown logger backend {backend!r}")
    if state and state.get("exp_name") == name and hasattr(logger, "load_state_dict"):
        logger.load_state_dict(state)
    return logger


def _tensorboard_logger(name: str, log_dir: Path, *, purge_step: int | None) -> Logger:
    """TorchRL's ``TensorboardLogger`` whose writer hides events at steps ≥ ``purge_step``."""
    from torchrl.record.loggers.tensorboard import TensorboardLogger

    class _Logger(TensorboardLogger):
        def _create_experiment(self):
            from torch.utils.tensorboard import SummaryWriter

            return SummaryWriter(
                log_dir=str(Path(self.log_dir) / self.exp_name), purge_step=purge_step
            )

    return _Logger(exp_name=name, log_dir=str(log_dir))


def _wandb_key_available() -> bool:
    if os.environ.get("WANDB_API_KEY"):
        return True
    netrc = Path.home() / ".netrc"
    return netrc.exists() and "api.wandb.ai" in netrc.read_text(errors="ignore")
