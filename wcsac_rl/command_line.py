"""``wcsac-train``'s command line checked before Hydra runs: each refusal one line
naming the override (Hydra's own are stacks of lines), nothing written. The kit reads
the overrides once, with Hydra's own override grammar, and hands that reading to every
check (Hydra reads them again itself to compose the run's config). Imports only Hydra
until a check needs more, so that ``--help`` answers at once.

Why before Hydra, rather than rewording Hydra's own errors: Hydra 1.3's ``hydra.main``
prints its refusals itself and exits (``run_and_report``; the exception reaches the
caller only under ``HYDRA_FULL_ERROR=1``, a setting its launchers' processes inherit),
some of its errors do not name what the message needs (``=5`` fails as a bare
``ValueError`` naming no override; an unknown key's config is reached only through the
node inside OmegaConf's exception), and its sweeper composes each job but validates none
of its values, after it has written the sweep directory and its ``multirun.yaml``. A
sweeper of the kit's own would have to be a ``hydra_plugins`` package, and a sweep run
by another sweeper would go unchecked."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from omegaconf import DictConfig

from wcsac_rl.config_dir import CONF_DIR

__all__ = [
    "check_command_line",
    "check_interpolations",
    "check_output_dirs",
    "check_override_syntax",
    "check_sweep_jobs",
    "compose_config",
]


def check_command_line(argv: list[str]) -> bool:
    """Refuse a command line Hydra would refuse in a stack of lines (an override it
    cannot read, a key no chosen config has: ``algo.batchsize=64`` names the closest key,
    a directory it cannot write, a sweep without ``-m``, a bad value in any job of a
    ``-m`` sweep) in one ``error:`` line and exit code 1, before Hydra writes anything.
    Returns whether the command runs a job: ``--help``, ``--info``, ``--cfg``, shell
    completion and a malformed flag are Hydra's to answer (untouched, and fast)."""
    import sys

    from hydra._internal.utils import get_args_parser

    try:
        args, _ = get_args_parser().parse_known_args(argv)
    except SystemExit:  # a malformed flag: Hydra answers it
        return False
    if args.help or args.hydra_help or args.info or args.cfg or args.shell_completion:
        return False
    from wcsac_rl.training.config_keys import check_override_keys
    from wcsac_rl.training.errors import ConfigError

    overrides = list(args.overrides)
    try:
        parsed = check_override_syntax(overrides)  # (the one reading, for every check)
        check_interpolations(parsed)
        check_override_keys(parsed)
        check_output_dirs(parsed)
        check_sweep_jobs(parsed, multirun=bool(args.multirun))
    except ConfigError as err:
        sys.exit(f"error: {err}")
    return True


def check_sweep_jobs(overrides: Sequence[Any], *, multirun: bool = True) -> None:
    """Without ``-m`` a sweep (``algo.lr=1,2``) is one line saying to add it or to quote
    the value. With ``-m``, every value of each sweep the command line names is checked
    before the launcher starts a job (``seed=1,abc`` is refused before seed 1 trains):
    the config of each value, the other sweeps at their first, composed and validated. A
    sweep that resumes runs (``resume=...``) is checked by each job against its own run.
    ``overrides``: strings, or Hydra's parsed ``Override`` objects (what Hydra cannot
    parse is left to its own message)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    from wcsac_rl.training.config import validate_config
    from wcsac_rl.training.config_keys import parse_overrides
    from wcsac_rl.training.errors import ConfigError

    parsed = parse_overrides(overrides)
    if parsed is None:
        return
    lines = [o.input_line for o in parsed]
    sweeps = [o for o in parsed if o.is_sweep_override() and not o.is_hydra_override()]
    given = {o.get_key_element() for o in sweeps}
    sweeps += [  # an experiment's own sweep (hydra.sweeper.params), where it runs one
        o
        for o in OverridesParser.create().parse_overrides(_config_sweeps(lines, multirun))
        if o.get_key_element() not in given
    ]
    if sweeps and not multirun and sweeps[0].input_line in lines:
        key, _, value = sweeps[0].input_line.partition("=")
        raise ConfigError(
            f"{sweeps[0].input_line} is a sweep of values: add -m (--multirun) to run one job "
            f"for each, or quote the value to give it whole: \"{key}='{value}'\""
        )
    if not sweeps or any(o.get_key_element().lstrip("+~") == "resume" for o in parsed):
        return
    fixed = [o.input_line for o in parsed if not o.is_sweep_override()]
    first = {id(o): next(iter(o.sweep_string_iterator())) for o in sweeps}
    for sweep in sweeps:
        for value in sweep.sweep_string_iterator():
            job = [f"{o.get_key_element()}={value if o is sweep else first[id(o)]}" for o in sweeps]
            validate_config(_job_config(fixed, job))


def _config_sweeps(overrides: list[str], multirun: bool) -> list[str]:
    """The sweep an experiment's config runs (``hydra.sweeper.params`` as overrides,
    ``+row=sac,wcsac_0.1``), where the command runs in MULTIRUN mode: none otherwise."""
    from omegaconf import OmegaConf

    if not any(o.lstrip("+").startswith("experiment=") for o in overrides):
        return []
    try:
        hydra_cfg = _compose(overrides, return_hydra_config=True).hydra
    except Exception:  # (composition errors: the command itself reports them)
        return []
    if not (multirun or str(hydra_cfg.mode) == "RunMode.MULTIRUN"):
        return []
    params = OmegaConf.to_container(hydra_cfg.sweeper.get("params") or {}, resolve=False)
    return [f"{key}={value}" for key, value in params.items()]


def _job_config(fixed: list[str], job: list[str]) -> DictConfig:
    """The config of one job of a sweep, a job that cannot be composed one line naming it."""
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    from wcsac_rl._messages import first_line
    from wcsac_rl.training.errors import ConfigError

    try:
        return compose_config(*fixed, *job)
    except (HydraException, OmegaConfBaseException) as err:
        cause = f" ({first_line(err.__cause__)})" if err.__cause__ is not None else ""
        raise ConfigError(
            f"the sweep's job {' '.join(job)} cannot be composed: {first_line(err)}{cause}; "
            "give that option only to the jobs that have it (a sweep of fewer rows)"
        ) from None


def check_override_syntax(overrides: list[str]) -> list[Any]:
    """The overrides read by Hydra's grammar (Hydra's ``Override`` objects, what the other
    checks are given). Refused in one line naming it: an override that grammar cannot
    read (a path with a newline, a character outside its lexer's such as ``ü``) and one
    that names no key (``=5``); Hydra's own refusals are stacks of lines (or a traceback)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    from wcsac_rl.training.errors import ConfigError

    for override in overrides:
        key, sep, _ = override.partition("=")
        if sep and not key.lstrip("+~").strip():
            raise ConfigError(f"cannot read the override {override!r}: it names no key (key=value)")
    try:
        return OverridesParser.create().parse_overrides(list(overrides))
    except (HydraException, ValueError) as err:
        override = getattr(err, "override", None) or " ".join(overrides)
        reason = (str(err).strip().splitlines() or [type(err).__name__])[0]
        reason = reason.split(":", 1)[0] if reason.startswith("Lexer") else reason
        key = override.split("=", 1)[0]
        raise ConfigError(
            f"cannot read the override {override!r} ({reason}): quote its value inside "
            f"the argument, e.g. \"{key}='...'\", or choose a value without newlines or "
            "characters outside ASCII"
        ) from None


def _values(overrides: Sequence[Any]) -> list[tuple[str, str]]:
    """``(key, value as written)`` of each override that sets a value (not ``~key``), as
    Hydra's grammar reads them (strings are parsed; nothing where Hydra cannot)."""
    from wcsac_rl.training.config_keys import parse_overrides

    parsed = parse_overrides(overrides) or []
    return [
        (o.key_or_group, o.get_value_string())
        for o in parsed
        if not o.is_delete() and "=" in (o.input_line or "")
    ]


def check_interpolations(overrides: Sequence[Any]) -> None:
    """Refuse, in one line naming the key and the variable, an override whose
    interpolation cannot resolve: ``${oc.env:NAME}`` of an unset variable without a
    default, or a key that refers to itself (``seed=${seed}``). Hydra would resolve
    them while making the run's directory, in its own stack of lines. ``overrides``:
    strings, or Hydra's parsed ``Override`` objects."""
    import os
    import re

    from wcsac_rl.training.errors import ConfigError

    for key, value in _values(overrides):
        if key == "run_name" and "${" not in value:
            from wcsac_rl.training.config import check_run_name  # (imports torch)

            check_run_name(value.strip("'\""))  # (before Hydra makes outputs/<date>/<name>)
        if "${" not in value:
            continue
        for name, default in re.findall(r"\$\{oc\.env:\s*([^,}\s]+)\s*(,[^}]*)?\}", value):
            if not default and name not in os.environ:
                raise ConfigError(
                    f"{key}={value}: the environment variable {name} is not set (set it, "
                    f"or give a default: ${{oc.env:{name},<default>}})"
                )
        if re.search(r"\$\{\s*" + re.escape(key) + r"\s*\}", value):
            raise ConfigError(f"{key}={value} refers to itself; give {key} a value")


def check_output_dirs(overrides: Sequence[Any]) -> None:
    """Refuse, in one line, a run or sweep directory that cannot be written (a read-only
    file system, another user's directory) before Hydra tries to create it (its own
    failure is a stack of lines). Directories given with interpolations are checked up
    to their first one; without ``hydra.run.dir`` / ``hydra.sweep.dir``, Hydra writes
    below the current directory. ``overrides``: strings, or Hydra's parsed ``Override``
    objects."""
    from wcsac_rl.training.errors import ConfigError
    from wcsac_rl.training.run_dir import unwritable_reason

    given = {
        key: value.strip("'\"")
        for key, value in _values(overrides)
        if key in ("hydra.run.dir", "hydra.sweep.dir")
    }
    for key, value in (given or {"the current directory": "."}).items():
        literal = value.split("${", 1)[0] or "."
        reason = unwritable_reason(literal)
        if reason is not None:
            where = f"{key}={value}" if key != "the current directory" else key
            raise ConfigError(
                f"cannot write the run's directory ({where}): {reason}; choose a directory "
                "you can write (hydra.run.dir=..., or hydra.sweep.dir=... for a sweep)"
            )


def compose_config(*overrides: str) -> DictConfig:
    """The config the command line ``wcsac-train <overrides>`` would train, for
    :func:`~wcsac_rl.train.run_training` (an unknown key is refused in one line naming
    the closest).

    >>> cfg = compose_config("algo=sac_lag", "env=tiny", "seed=3")
    >>> cfg.algo.name, cfg.env.name, cfg.seed, cfg.run_name
    ('sac_lag', 'tiny', 3, 'sac_lag_tiny_seed3')
    """
    from wcsac_rl.training.config_keys import check_override_keys

    check_override_keys(list(overrides))
    return _compose(list(overrides))


def _compose(overrides: list[str], *, return_hydra_config: bool = False) -> DictConfig:
    """``conf/config.yaml`` composed with ``overrides`` by Hydra's compose API (with
    ``return_hydra_config``: its ``hydra`` node too); a Hydra app calling this keeps its
    own state."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    was_initialized = GlobalHydra.instance().is_initialized()
    previous = GlobalHydra.instance().config_loader() if was_initialized else None
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            return compose("config", overrides, return_hydra_config=return_hydra_config)
    finally:
        GlobalHydra.instance().clear()
        if previous is not None:
            GlobalHydra.instance().initialize(previous)
