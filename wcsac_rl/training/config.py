"""Validation of a training configuration: every user mistake becomes one clear line."""

from __future__ import annotations

from collections.abc import Mapping
from types import MappingProxyType
from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf

from wcsac_rl.objectives.budget import validate_cost_limit
from wcsac_rl.objectives.risk import validate_risk_level

__all__ = [
    "ALGOS",
    "OFF_POLICY_ALGOS",
    "ON_POLICY_ALGOS",
    "SAVED_RUN_OPTIONS",
    "ConfigError",
    "TrainingError",
    "algo_option",
    "validate_config",
]

OFF_POLICY_ALGOS = ("wcsac", "sac_lag", "sac")
ON_POLICY_ALGOS = ("cpo",)
ALGOS = (*OFF_POLICY_ALGOS, *ON_POLICY_ALGOS, "random")


class ConfigError(ValueError):
    """A configuration a run cannot start from; the message says what to change."""


class TrainingError(RuntimeError):
    """A run that cannot go on (or cannot be saved); the message says why and what to do.

    Raised after the last good checkpoint is safe: ``train.py`` prints it as one line.
    """


def _positive_int(cfg: Mapping[str, Any], key: str, *, allow_zero: bool = False) -> None:
    value = OmegaConf.select(cfg, key) if isinstance(cfg, DictConfig) else cfg.get(key)
    ok = isinstance(value, int) and not isinstance(value, bool)
    ok = ok and (value >= 0 if allow_zero else value > 0)
    if not ok:
        bound = ">= 0" if allow_zero else "> 0"
        raise ConfigError(f"{key} must be an integer {bound}, got {value!r}")


def _validate_cpo(cfg: DictConfig) -> None:
    algo = cfg.algo
    for key in ("gamma", "lmbda", "cost_gamma", "cost_lmbda"):
        if not 0.0 <= float(algo[key]) <= 1.0:
            raise ConfigError(f"algo.{key} must be in [0, 1], got {algo[key]}")
    for key in ("max_kl", "value_lr"):
        if not float(algo[key]) > 0:
            raise ConfigError(f"algo.{key} must be > 0, got {algo[key]}")
    if not float(algo.damping) >= 0:
        raise ConfigError(f"algo.damping must be >= 0, got {algo.damping}")
    if not float(algo.entropy_coeff) >= 0:
        raise ConfigError(f"algo.entropy_coeff must be >= 0, got {algo.entropy_coeff}")
    if not 0.0 < float(algo.backtrack_coeff) < 1.0:
        raise ConfigError(f"algo.backtrack_coeff must be in (0, 1), got {algo.backtrack_coeff}")
    for key in ("cg_iters", "backtrack_iters", "value_iters"):
        _positive_int(cfg, f"algo.{key}")
    if algo.value_batch_size is not None:
        _positive_int(cfg, "algo.value_batch_size")


def validate_config(cfg: DictConfig) -> None:
    """Raise :class:`ConfigError` if ``cfg`` cannot give a sensible run. Does no work."""
    from wcsac_rl.envs import PRESET_NAMES  # local: importing envs loads MuJoCo

    algo = cfg.algo.get("name")
    if algo not in ALGOS:
        raise ConfigError(f"unknown algo {algo!r}; choose one of {', '.join(ALGOS)}")
    env = cfg.env.get("name")
    if env not in PRESET_NAMES:
        raise ConfigError(f"unknown env {env!r}; choose one of {', '.join(PRESET_NAMES)}")
    try:
        validate_risk_level(cfg.risk_level)
        if algo in ("wcsac", "sac_lag"):
            validate_risk_level(cfg.algo.risk_level)
    except ValueError as err:
        raise ConfigError(str(err)) from None
    if algo == "sac_lag" and float(cfg.algo.risk_level) != 1.0:
        raise ConfigError(
            "algo=sac_lag is risk-neutral (algo.risk_level=1); use algo=wcsac for α < 1"
        )
    try:
        validate_cost_limit(cfg.cost_limit)
    except ValueError as err:
        raise ConfigError(str(err)) from None
    _positive_int(cfg, "seed", allow_zero=True)  # gymnasium and NumPy need seeds >= 0
    for key in ("total_frames", "epoch_frames", "threads", "checkpoint_every_epochs"):
        _positive_int(cfg, key)
    if cfg.get("max_nonfinite_updates") is not None:
        _positive_int(cfg, "max_nonfinite_updates")
    _positive_int(cfg, "eval_episodes", allow_zero=True)
    keep = cfg.get("keep_checkpoints_at") or []
    if not isinstance(keep, (list, tuple, ListConfig)) or not all(
        isinstance(e, int) and not isinstance(e, bool) and e >= 1 for e in keep
    ):
        raise ConfigError(
            f"keep_checkpoints_at must be a list of epochs >= 1 (e.g. [1,5]), got {keep!r}"
        )
    for key in ("compile", "retain_freed_memory", "save_replay_buffer", "progress_bar"):
        value = cfg.get(key, False)
        if not isinstance(value, bool):
            raise ConfigError(f"{key} must be true or false, got {value!r}")
    if cfg.env.get("max_episode_steps") is not None:
        _positive_int(cfg, "env.max_episode_steps")
    collector = cfg.algo.collector
    _positive_int(cfg, "algo.collector.num_envs")
    _positive_int(cfg, "algo.collector.frames_per_batch")
    if collector.frames_per_batch % collector.num_envs:
        raise ConfigError(
            f"algo.collector.frames_per_batch ({collector.frames_per_batch}) must be a multiple "
            f"of algo.collector.num_envs ({collector.num_envs})"
        )
    if collector.get("env_backend", "serial") not in ("serial", "parallel"):
        raise ConfigError(
            f"algo.collector.env_backend must be 'serial' or 'parallel', got {collector.env_backend!r}"
        )
    if algo in OFF_POLICY_ALGOS:
        _positive_int(cfg, "algo.batch_size")
        _positive_int(cfg, "algo.buffer_size")
        _positive_int(cfg, "algo.collector.init_random_frames", allow_zero=True)
        if not 0 < float(collector.utd_ratio):
            raise ConfigError(f"algo.collector.utd_ratio must be > 0, got {collector.utd_ratio}")
        if not 0.0 < float(cfg.algo.tau) <= 1.0:
            raise ConfigError(f"algo.tau must be in (0, 1], got {cfg.algo.tau}")
        if not 0.0 <= float(cfg.algo.gamma) <= 1.0:
            raise ConfigError(f"algo.gamma must be in [0, 1], got {cfg.algo.gamma}")
        if not float(cfg.algo.lr) > 0:
            raise ConfigError(f"algo.lr must be > 0, got {cfg.algo.lr}")
        actor_lr = cfg.algo.get("actor_lr")
        if actor_lr is not None and not (
            isinstance(actor_lr, (int, float)) and not isinstance(actor_lr, bool) and actor_lr > 0
        ):
            raise ConfigError(f"algo.actor_lr must be null (= algo.lr) or > 0, got {actor_lr!r}")
    if algo in ("wcsac", "sac_lag"):
        collector = cfg.algo.collector
        learning_frames = max(0, int(cfg.total_frames) - int(collector.init_random_frames))
        _validate_safety_keys(cfg.algo, updates=int(learning_frames * float(collector.utd_ratio)))
    if algo in ON_POLICY_ALGOS:
        _validate_cpo(cfg)
    if cfg.logger.backend not in ("csv", "wandb", "tensorboard", "none"):
        raise ConfigError(
            f"logger.backend must be csv, wandb, tensorboard or none, got {cfg.logger.backend!r}"
        )
    _check_logger_package(str(cfg.logger.backend))
    _check_device(str(cfg.device))


LOGGER_PACKAGES = {"tensorboard": "tensorboard", "wandb": "wandb"}
"""The package each optional logger backend needs (also the name of its pip extra)."""


def _check_logger_package(backend: str) -> None:
    import importlib.util

    package = LOGGER_PACKAGES.get(backend)
    if package is not None and importlib.util.find_spec(package) is None:
        raise ConfigError(
            f"logger={backend} needs the {package} package, which is not installed: "
            f'pip install -e ".[{package}]" (or pip install {package}), or use logger=csv'
        )


def _check_device(device: str) -> None:
    import torch

    kind, _, index = device.partition(":")
    if kind not in ("cpu", "cuda", "mps") or (index and not index.isdigit()):
        raise ConfigError(f"device must be cpu, cuda[:N] or mps, got {device!r}")
    if kind == "cpu":
        return
    if kind == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if count == 0:
            build = (
                "a CPU-only build" if torch.version.cuda is None else f"CUDA {torch.version.cuda}"
            )
            raise ConfigError(
                f"device={device} but this machine has no CUDA device (torch {torch.__version__}, "
                f"{build}); use device=cpu"
            )
        if index and int(index) >= count:
            raise ConfigError(
                f"device={device} but only {count} CUDA device(s) are visible (cuda:0"
                f"{f'..cuda:{count - 1}' if count > 1 else ''}); choose one of them"
            )
    elif not torch.backends.mps.is_available():
        raise ConfigError("device=mps but MPS is not available on this machine; use device=cpu")


SAVED_RUN_OPTIONS = MappingProxyType(
    {
        "variance_target": "moment",
        "kappa_states": "replay",
        "kappa_statistic": "mean",
        "kappa_signal": "critic",
        "cost_gamma": None,
        "cost_bootstrap_truncated": True,  # (it bootstrapped across time limits)
        "cost_n_steps": 1,
        "nonnegative_cost": False,
        "safety_critic": "gaussian",
        "kappa_rule": "gradient",
        "kappa_episode_statistic": "cvar",
    }
)
"""What a run saved before one of these ``algo`` options existed did: its value for it
(a resumed or evaluated run keeps training as it did)."""


def algo_option(algo: DictConfig, key: str) -> Any:
    """``algo[key]``, or what a run saved before the option existed did
    (:data:`SAVED_RUN_OPTIONS`)."""
    return algo.get(key, SAVED_RUN_OPTIONS.get(key))


def _validate_safety_keys(algo: DictConfig, *, updates: int) -> None:
    """The WCSAC / SAC-Lag options of ``conf/algo`` (the loss would refuse them later).

    With ``safety_critic=iqn`` the variance options (``variance``, ``variance_loss``,
    ``variance_target``) are not used: they configure the Gaussian critic."""
    from wcsac_rl.modules.safety_critic import SAFETY_CRITIC_KINDS
    from wcsac_rl.objectives.constraint import (
        CONSTRAINT_RULES,
        KAPPA_PARAMETRIZATIONS,
        PIDGains,
    )
    from wcsac_rl.objectives.episode_costs import EPISODE_STATISTICS
    from wcsac_rl.objectives.wcsac import (
        KAPPA_ACTIONS,
        KAPPA_SIGNALS,
        KAPPA_STATES,
        KAPPA_STATISTICS,
        VARIANCE_LOSSES,
        VARIANCE_TARGETS,
    )

    choices = {
        "variance_loss": VARIANCE_LOSSES,
        "variance_target": VARIANCE_TARGETS,
        "kappa_actions": KAPPA_ACTIONS,
        "kappa_states": KAPPA_STATES,
        "kappa_statistic": KAPPA_STATISTICS,
        "kappa_parametrization": KAPPA_PARAMETRIZATIONS,
        "kappa_signal": KAPPA_SIGNALS,
        "kappa_rule": CONSTRAINT_RULES,
        "kappa_episode_statistic": EPISODE_STATISTICS,
    }
    for key, allowed in choices.items():
        if algo_option(algo, key) not in allowed:
            raise ConfigError(
                f"algo.{key} must be one of {', '.join(allowed)}, got {algo.get(key)!r}"
            )
    if algo_option(algo, "kappa_signal") != "critic":
        if algo_option(algo, "kappa_states") != "initial":
            raise ConfigError(
                f"algo.kappa_signal={algo.kappa_signal} needs algo.kappa_states=initial (episode "
                f"costs are compared with the episodic limit d), got {algo.kappa_states}"
            )
        window = algo.get("kappa_episode_window")
        if not isinstance(window, int) or isinstance(window, bool) or window < 1:
            raise ConfigError(
                f"algo.kappa_episode_window must be an integer >= 1 (episodes), got {window!r}"
            )
    pid = algo.get("pid")
    if pid is not None or algo_option(algo, "kappa_rule") == "pid":
        # (checked under either rule: a wrong gain is wrong whichever rule runs)
        if not isinstance(pid, Mapping):
            raise ConfigError(f"algo.pid must hold the PID gains, got {pid!r}")
        known = set(PIDGains.__dataclass_fields__)
        unknown = sorted(set(pid) - known)
        if unknown:
            raise ConfigError(
                f"unknown PID option algo.pid.{unknown[0]}; the gains are "
                f"{', '.join(sorted(known))}"
            )
        try:
            gains = PIDGains(**OmegaConf.to_container(pid, resolve=True))
        except (TypeError, ValueError) as err:
            raise ConfigError(f"algo.{err}") from None
        if gains.d_delay > updates:
            raise ConfigError(
                f"algo.pid.d_delay={gains.d_delay} updates is longer than the run's "
                f"{updates} updates: the derivative term would never act"
            )
    if not float(algo.kappa_init) > 0:
        raise ConfigError(
            f"algo.kappa_init must be > 0 (κ is a Lagrange multiplier), got {algo.kappa_init}"
        )
    if not float(algo.damp_scale) >= 0:
        raise ConfigError(f"algo.damp_scale must be >= 0, got {algo.damp_scale}")
    cost_gamma = algo.get("cost_gamma")
    if cost_gamma is not None and not 0.0 <= float(cost_gamma) <= 1.0:
        raise ConfigError(f"algo.cost_gamma must be null or in [0, 1], got {cost_gamma}")
    if not isinstance(algo_option(algo, "cost_bootstrap_truncated"), (bool, type(None))):
        raise ConfigError(
            "algo.cost_bootstrap_truncated must be null, true or false, got "
            f"{algo.get('cost_bootstrap_truncated')!r}"
        )
    if not isinstance(algo_option(algo, "nonnegative_cost"), bool):
        raise ConfigError(
            f"algo.nonnegative_cost must be true or false, got {algo.get('nonnegative_cost')!r}"
        )
    kind = algo_option(algo, "safety_critic")
    if kind not in SAFETY_CRITIC_KINDS:
        raise ConfigError(
            f"algo.safety_critic must be one of {', '.join(SAFETY_CRITIC_KINDS)}, got {kind!r}"
        )
    if kind == "iqn":
        iqn = algo.get("iqn") or {}
        for key in ("num_quantiles", "num_target_quantiles", "num_cosines"):
            value = iqn.get(key)
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ConfigError(f"algo.iqn.{key} must be an integer >= 1, got {value!r}")
        if not isinstance(iqn.get("huber_kappa"), (int, float)) or not iqn.huber_kappa > 0:
            raise ConfigError(f"algo.iqn.huber_kappa must be > 0, got {iqn.get('huber_kappa')!r}")
    n_steps = algo_option(algo, "cost_n_steps")
    if not isinstance(n_steps, int) or isinstance(n_steps, bool) or n_steps < 1:
        raise ConfigError(f"algo.cost_n_steps must be an integer >= 1, got {n_steps!r}")
    if not float(algo.kappa_lr_scale) > 0:
        raise ConfigError(f"algo.kappa_lr_scale must be > 0, got {algo.kappa_lr_scale}")
