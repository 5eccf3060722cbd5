"""Validation of a training configuration: every user mistake becomes one clear line."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf

from wcsac_rl.cli_args import SEED_MAX, machine_cores
from wcsac_rl.envs.presets import has_goals
from wcsac_rl.objectives.budget import validate_cost_limit
from wcsac_rl.objectives.risk import validate_risk_level
from wcsac_rl.options import ALPHA_INIT, Option, SafetyOptions, check_value, read_options
from wcsac_rl.training.errors import ConfigError, TrainingError
from wcsac_rl.training.registry import ALGORITHMS, Algorithm, algorithm, resolve

__all__ = [
    "SIZE_LIMITS",
    "ConfigError",
    "TrainingError",
    "check_cpo",
    "check_sizes",
    "safety_options",
    "validate_config",
]


def _get(cfg: Mapping[str, Any], key: str) -> Any:
    """``cfg``'s entry at the dotted ``key`` (``None`` where there is none)."""
    if isinstance(cfg, DictConfig):
        return OmegaConf.select(cfg, key)
    node: Any = cfg
    for part in key.split("."):
        node = node.get(part) if isinstance(node, Mapping) else None
    return node


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _spec(kind: str, **spec: Any) -> Option:
    """What a run's setting may be: an :class:`~wcsac_rl.options.Option` with no ceiling
    (a learning rate or a count is not one of the losses' weights)."""
    return Option("", kind, reader="config", ceiling=None, **spec)


_COUNT = _spec("integer", low=0)
_POSITIVE = _spec("integer", low=0, low_open=True)
_RATE = _spec("number", low=0.0, low_open=True)
_FRACTION = _spec("number", low=0.0, high=1.0)
_WEIGHT = _spec("number", low=0.0)
_REAL = _spec("number")
_FLAG = _spec("flag")

SIZE_LIMITS = {
    "algo.network.width": _spec("integer", low=1, high=16_384),
    "algo.network.depth": _spec("integer", low=0, high=64),
    "env.max_episode_steps": _spec("integer", low=1, high=1_000_000),
}
"""The largest network and episode a config may ask for (a 16 384-wide layer is a GiB of
weights; the paper's are 256 wide, its episodes 1 000 steps): checked for a new run and
for a stored one before anything is built from it (:func:`check_sizes`)."""

CPO_OPTIONS = {
    **{f"algo.{key}": _FRACTION for key in ("gamma", "lmbda", "cost_gamma", "cost_lmbda")},
    "algo.max_kl": _RATE,
    "algo.value_lr": _RATE,
    "algo.damping": _WEIGHT,
    "algo.entropy_coeff": _WEIGHT,
    "algo.backtrack_coeff": _spec("number", low=0.0, high=1.0, low_open=True, high_open=True),
    **{f"algo.{key}": _POSITIVE for key in ("cg_iters", "backtrack_iters", "value_iters")},
    "algo.normalize_advantage": _FLAG,
    "algo.center_cost_advantage": _FLAG,
    "algo.network.log_std_init": _REAL,
}
"""CPO's own settings (its registry entry's ``check``: :func:`check_cpo`)."""

OFF_POLICY_OPTIONS = {
    "algo.batch_size": _POSITIVE,
    "algo.buffer_size": _POSITIVE,
    "algo.collector.init_random_frames": _COUNT,
    "algo.collector.utd_ratio": _RATE,
    "algo.tau": _spec("number", low=0.0, high=1.0, low_open=True),
    "algo.gamma": _FRACTION,
    "algo.lr": _RATE,
    "algo.actor_lr": _spec("number", low=0.0, low_open=True, nullable=True),  # null: algo.lr
    "algo.alpha_init": ALPHA_INIT,
    "algo.network.log_std_min": _REAL,
    "algo.network.log_std_max": _REAL,
}
"""The SAC family's schedule, optimiser, entropy weight and policy's spread."""


def _check(cfg: Mapping[str, Any], key: str, spec: Option) -> Any:
    """``cfg``'s entry at ``key``, or one :class:`ConfigError` line naming the key and
    what ``spec`` allows (:func:`~wcsac_rl.options.check_value`)."""
    value = _get(cfg, key)
    try:
        check_value(key, value, spec)
    except ValueError as err:
        raise ConfigError(str(err)) from None
    return value


def _check_all(cfg: Mapping[str, Any], specs: Mapping[str, Option]) -> None:
    for key, spec in specs.items():
        _check(cfg, key, spec)


def check_sizes(cfg: Mapping[str, Any], source: Any) -> None:
    """A stored config's sizes (:data:`SIZE_LIMITS`) within their limits before a network
    or an env is built from it: one :class:`ConfigError` line naming ``source``."""
    for key, spec in SIZE_LIMITS.items():
        if _get(cfg, key) is None:
            continue
        try:
            _check(cfg, key, spec)
        except ConfigError as err:
            raise ConfigError(f"{source}: its config's {err}: not built") from None


def check_cpo(cfg: DictConfig) -> None:
    """CPO's own options (its registry entry's ``check``)."""
    _check_all(cfg, CPO_OPTIONS)
    if cfg.algo.value_batch_size is not None:
        _check(cfg, "algo.value_batch_size", _POSITIVE)
    _validate_network(cfg)


def _validate_network(cfg: DictConfig) -> None:
    """``algo.network``: every MLP's width, depth and activation."""
    from wcsac_rl.modules._mlp import ACTIVATION_NAMES

    _check(cfg, "algo.network.width", SIZE_LIMITS["algo.network.width"])
    _check(cfg, "algo.network.depth", SIZE_LIMITS["algo.network.depth"])
    _check(cfg, "algo.network.activation", _spec("choice", choices=ACTIVATION_NAMES))


def _validate_off_policy(cfg: DictConfig) -> None:
    """The SAC family's options (:data:`OFF_POLICY_OPTIONS`), then their relations."""
    _check_all(cfg, OFF_POLICY_OPTIONS)
    batch, buffer = cfg.algo.batch_size, cfg.algo.buffer_size
    if batch > buffer:
        raise ConfigError(
            f"algo.batch_size ({batch}) must be <= algo.buffer_size ({buffer}): a batch is "
            "sampled from the replay buffer"
        )
    if cfg.algo.target_entropy != "auto" and not _REAL.accepts(cfg.algo.target_entropy):
        raise ConfigError(
            f"algo.target_entropy must be auto (-|A|) or a finite number, got "
            f"{cfg.algo.target_entropy!r}"
        )
    _validate_network(cfg)
    low, high = cfg.algo.network.log_std_min, cfg.algo.network.log_std_max
    if not low < high:
        raise ConfigError(
            f"algo.network.log_std_min ({low:g}) must be < algo.network.log_std_max ({high:g})"
        )


NODES = ("algo", "env", "logger", "algo.collector")
"""Entries that hold options (a value there is a mistake: ``algo.collector=4``)."""


def _validate_choices(cfg: DictConfig) -> Algorithm:
    """The algorithm and env must be known ones; returns the algorithm's entry."""
    from wcsac_rl.envs import PRESET_NAMES  # local: importing envs loads MuJoCo

    for node in (*NODES, *(("algo.network",) if _get(cfg, "algo.network") is not None else ())):
        value = _get(cfg, node)
        if not isinstance(value, Mapping):
            raise ConfigError(f"{node} must hold its options (a mapping), got {value!r}")
    algo = algorithm(cfg.algo.get("name"))
    env = cfg.env.get("name")
    if env == "gymnasium":
        _validate_user_env(cfg)
    elif env not in PRESET_NAMES:
        raise ConfigError(
            f"unknown env {env!r}; choose one of {', '.join(PRESET_NAMES)}, or gymnasium "
            "(your own: env=gymnasium env.id=<registered id | module:callable>)"
        )
    return algo


def _validate_user_env(cfg: DictConfig) -> None:
    """``env=gymnasium``: ``env.id`` names the env, ``env.cost_key`` its cost's info entry."""
    env_id = cfg.env.get("id")
    if not isinstance(env_id, str) or not env_id.strip():
        raise ConfigError(
            f"env=gymnasium needs env.id=<registered gymnasium id | module:callable>, got "
            f"{env_id!r} (docs/own_environment.md)"
        )
    cost_key = cfg.env.get("cost_key")
    if not isinstance(cost_key, str) or not cost_key:
        raise ConfigError(f"env.cost_key must name the info entry of the cost, got {cost_key!r}")


def _validate_risk(cfg: DictConfig) -> None:
    """The run's α and d (``algo.risk_level``: a safety option, :func:`safety_options`)."""
    try:
        validate_risk_level(cfg.risk_level)
        validate_cost_limit(cfg.cost_limit)
    except ValueError as err:
        raise ConfigError(str(err)) from None


def check_run_name(value: Any) -> None:
    """``run_name`` names a directory inside ``outputs/<date>/`` and the logger's
    ``logs/<run_name>/``: a name, not a path (``../../../x`` would put them elsewhere)."""
    text = str(value)
    if not text.strip() or "/" in text or "\\" in text or text in (".", "..") or "\n" in text:
        raise ConfigError(
            f"run_name must be a name without '/' (it names the run's directory and its "
            f"logs/<run_name>/), got {value!r}; choose where the run goes with hydra.run.dir"
        )


def _validate_run(cfg: DictConfig) -> None:
    """The run's schedule, checkpoints and switches (the top-level keys)."""
    seed = _get(cfg, "seed")
    _check(cfg, "seed", _COUNT)  # gymnasium and NumPy need seeds >= 0
    if seed > SEED_MAX:
        raise ConfigError(f"seed must be at most 2**63 - 1 = {SEED_MAX}, got {seed!r}")
    if cfg.get("run_name") is not None:  # (after the seed its default is made from)
        check_run_name(cfg.run_name)
    for key in ("total_frames", "epoch_frames", "threads", "checkpoint_every_epochs"):
        _check(cfg, key, _POSITIVE)
    cores = machine_cores()
    if cfg.threads > cores:
        raise ConfigError(
            f"threads={cfg.threads} is more than this machine's {cores} cores (torch threads "
            f"beyond them only wait for each other); choose threads <= {cores}"
        )
    if cfg.get("max_nonfinite_updates") is not None:
        _check(cfg, "max_nonfinite_updates", _POSITIVE)
    _check(cfg, "eval_episodes", _COUNT)
    keep = cfg.get("keep_checkpoints_at") or []
    if not isinstance(keep, (list, tuple, ListConfig)) or not all(
        _is_int(e) and e >= 1 for e in keep
    ):
        raise ConfigError(
            f"keep_checkpoints_at must be a list of epochs >= 1 (e.g. [1,5]), got {keep!r}"
        )
    for key in (
        "compile",
        "cudagraphs",
        "retain_freed_memory",
        "save_replay_buffer",
        "progress_bar",
        "trust_env_code",
    ):
        if key in cfg:
            _check(cfg, key, _FLAG)
    resume = cfg.get("resume")
    if resume is not None and not isinstance(resume, str):
        raise ConfigError(f"resume must be null, auto or a run directory, got {resume!r}")
    if cfg.env.get("max_episode_steps") is not None:
        _check(cfg, "env.max_episode_steps", SIZE_LIMITS["env.max_episode_steps"])
    kwargs = cfg.env.get("kwargs")
    if kwargs is not None and not isinstance(kwargs, Mapping):
        raise ConfigError(f"env.kwargs must be a mapping of env arguments, got {kwargs!r}")
    if kwargs and cfg.env.name != "gymnasium":
        _validate_preset_kwargs(str(cfg.env.name), kwargs)


def _validate_preset_kwargs(env: str, kwargs: Mapping) -> None:
    """A built-in env's ``env.kwargs`` are options its constructor takes (your own
    env's are yours: passed to it as they are)."""
    from wcsac_rl.envs.presets import preset_options  # local: importing envs loads MuJoCo

    options = preset_options(env)
    unknown = sorted(str(key) for key in kwargs if options is not None and key not in options)
    if unknown:
        raise ConfigError(
            f"env.kwargs.{unknown[0]}: env {env} has no option {unknown[0]!r} (its options: "
            f"{', '.join(sorted(options))})"
        )


def _validate_collector(cfg: DictConfig) -> None:
    collector = cfg.algo.collector
    envs = _check(cfg, "algo.collector.num_envs", _POSITIVE)
    frames = _check(cfg, "algo.collector.frames_per_batch", _POSITIVE)
    if frames % envs:
        raise ConfigError(
            f"algo.collector.frames_per_batch ({frames}) must be a multiple "
            f"of algo.collector.num_envs ({envs})"
        )
    if collector.get("env_backend", "serial") not in ("serial", "parallel"):
        raise ConfigError(
            f"algo.collector.env_backend must be 'serial' or 'parallel', got {collector.env_backend!r}"
        )


def _validate_interpolations(cfg: DictConfig) -> None:
    """Every ``${...}`` of the run's config resolves (Hydra's own node aside): one line
    naming the key, what it holds and why it does not (an unset environment variable, a
    key that refers to itself)."""
    raw = OmegaConf.to_container(cfg, resolve=False)

    def walk(node: Any, prefix: str) -> None:
        items = node.items() if isinstance(node, dict) else enumerate(node)
        for key, value in items:
            path = f"{prefix}{key}"
            if path == "hydra":
                continue
            if isinstance(value, (dict, list)):
                walk(value, f"{path}.")
            elif isinstance(value, str) and "${" in value:
                try:
                    OmegaConf.select(cfg, path, throw_on_resolution_failure=True)
                except Exception as err:
                    first = (str(err).strip().splitlines() or [type(err).__name__])[0]
                    first = first.split("resolving interpolation: ", 1)[-1].strip("\"'. ")
                    raise ConfigError(f"{path}={value} cannot be resolved: {first}") from None

    walk(raw, "")


def validate_config(cfg: DictConfig, *, check_keys: bool = True) -> None:
    """Raise :class:`ConfigError` if ``cfg`` cannot give a sensible run. Does no work.

    Every value is checked for its type and range (one line naming the key and what it
    may be), before anything is built; and, with ``check_keys``, every key must be one
    of the chosen algorithm's, env's and logger's defaults
    (:func:`~wcsac_rl.training.config_keys.check_known_keys`: a typo names the closest
    key), and ``algo.recipe`` must name the recipe files that shaped it. A resumed
    run's saved keys are checked against its checkpoint instead.
    """
    _validate_interpolations(cfg)
    algo = _validate_choices(cfg)
    _validate_risk(cfg)
    _validate_run(cfg)
    _validate_collector(cfg)
    if algo.off_policy:
        _validate_off_policy(cfg)
    if algo.safety_critic:
        collector = cfg.algo.collector
        learning_frames = max(0, cfg.total_frames - collector.init_random_frames)
        _validate_safety_keys(
            cfg.algo,
            algo,
            updates=int(learning_frames * float(collector.utd_ratio)),
            eval_episodes=int(cfg.eval_episodes),
            env=str(cfg.env.name),
        )
    if algo.check is not None:
        resolve(algo.check)(cfg)
    if cfg.logger.backend not in ("csv", "wandb", "tensorboard", "none"):
        raise ConfigError(
            f"logger.backend must be csv, wandb, tensorboard or none, got {cfg.logger.backend!r}"
        )
    _check_logger_package(str(cfg.logger.backend))
    _check_device(cfg.device)
    if cfg.get("replay_draw", "update") not in ("update", "round"):
        raise ConfigError(
            f"replay_draw must be update (each update draws its replay batch) or round "
            f"(a collected batch's updates draw theirs at once), got {cfg.replay_draw!r}"
        )
    if cfg.get("cudagraphs", False) and not str(cfg.device).startswith("cuda"):
        raise ConfigError(
            f"cudagraphs=true captures the update as a CUDA graph: it needs device=cuda[:N], "
            f"got device={cfg.device}"
        )
    _check_recipe_files(cfg, fresh=check_keys)
    if check_keys:
        from wcsac_rl.training.config_keys import check_known_keys

        check_known_keys(cfg)


def _check_recipe_files(cfg: DictConfig, *, fresh: bool) -> None:
    """Every layout recipe of ``conf/algo/layout/`` is one Hydra reads, and (``fresh``:
    a config composed now, not a saved run's) ``algo.recipe`` names the files that
    shaped ``algo`` (:mod:`wcsac_rl.recipes`)."""
    from wcsac_rl.config_dir import CONF_DIR
    from wcsac_rl.recipes import check_layouts, check_recipe

    if not (CONF_DIR / "algo").is_dir():
        return
    try:
        check_layouts(CONF_DIR)
        if fresh and "recipe" in cfg.algo:
            check_recipe(CONF_DIR, cfg.algo.recipe, cfg.env.name)
    except ValueError as err:
        raise ConfigError(str(err)) from None


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


def _check_device(device: Any) -> None:
    import torch

    if not isinstance(device, str):
        raise ConfigError(f"device must be cpu, cuda[:N] or mps, got {device!r}")
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


def safety_options(algo: DictConfig) -> SafetyOptions:
    """The WCSAC / SAC-Lag options of ``algo``, checked and typed
    (:func:`~wcsac_rl.options.read_options`), or one :class:`ConfigError` line naming
    ``algo.<key>`` (a bad value, or a missing one)."""
    try:
        return read_options(SafetyOptions, algo, prefix="algo.")
    except ValueError as err:
        raise ConfigError(str(err)) from None


def _validate_safety_keys(
    algo: DictConfig, entry: Algorithm, *, updates: int, eval_episodes: int, env: str
) -> None:
    """The WCSAC / SAC-Lag options of ``conf/algo``: every field of
    :class:`~wcsac_rl.options.SafetyOptions` and the relations between them
    (:func:`~wcsac_rl.options.read_options`: the loss checks with the same definitions),
    then what relates an option and the run. The variance options are checked with an
    IQN critic too and the PID gains under the gradient rule: a wrong value is wrong
    whichever runs."""
    options = safety_options(algo)
    if entry.risk_neutral and options.risk_level != 1.0:
        averse = " or ".join(f"algo={a.name}" for a in ALGORITHMS.values() if a.reads_risk_level)
        raise ConfigError(
            f"algo={entry.name} is risk-neutral (algo.risk_level=1); use {averse} for α < 1"
        )
    if options.kappa_test_window and not eval_episodes:
        raise ConfigError(
            "algo.kappa_test_window reads the test episodes, but eval_episodes=0 runs "
            "none: set eval_episodes > 0 or algo.kappa_test_window=0"
        )
    if options.kappa_hold_goal_rate > 0 and not has_goals(env):
        raise ConfigError(
            f"algo.kappa_hold_goal_rate={options.kappa_hold_goal_rate:g} holds κ until "
            f"the training episodes reach the goal, but env={env} reports no goals: κ "
            "would never move; set algo.kappa_hold_goal_rate=0"
        )
    # the derivative term acts only under the PID rule with kd > 0 (a gradient-rule run,
    # or kd = 0, never reads d_delay: a short run is no reason to refuse them)
    pid = options.pid
    if options.kappa_rule == "pid" and pid.kd > 0 and pid.d_delay > updates:
        raise ConfigError(
            f"algo.pid.d_delay={pid.d_delay} updates is longer than the run's "
            f"{updates} updates: the derivative term would never act"
        )
