"""Which config keys exist: a key the chosen algorithm's defaults do not have is a typo.

Hydra merges an added key (``+risk_levl=0.1``, ``+algo.batchsize=64``) into the config
without a word, and a run would then silently train with the defaults. The reference
is the default config of the run's own algorithm, env and logger, composed from
``conf/`` by Hydra (the algorithm groups have different keys: ``cpo`` has ``max_kl``,
``wcsac`` has ``kappa_init``): :func:`check_known_keys` refuses any other key in one
line naming the closest known one (``difflib``), and :func:`check_override_keys` does
the same for ``train.py``'s command line before Hydra composes it (Hydra's own refusal
of ``algo.batchsize=64`` names no alternative). The configs are read from
:data:`~wcsac_rl.config_dir.CONF_DIR`: ``conf/`` of a checkout, or the copy a
(non-editable) install ships inside the package.
"""

from __future__ import annotations

import difflib
import functools
import itertools
from collections.abc import Collection, Iterable, Iterator, Sequence
from typing import Any

from omegaconf import DictConfig, OmegaConf

from wcsac_rl.config_dir import CONF_DIR as _CONF_DIR
from wcsac_rl.training.errors import ConfigError
from wcsac_rl.training.registry import ALGORITHMS
from wcsac_rl.training.trust import TRUST_KEY

__all__ = [
    "CONF_DIR",
    "FREE_FORM_KEYS",
    "check_group_choices",
    "check_known_keys",
    "check_override_keys",
    "key_paths",
    "known_keys",
    "missing_keys",
    "parse_overrides",
    "unknown_keys",
]

CONF_DIR = _CONF_DIR
"""The config groups ``train.py`` composes (``conf/`` of a checkout, or the installed copy)."""

FREE_FORM_KEYS = ("env.kwargs",)
"""Entries whose own keys are the user's (forwarded to the gymnasium env's constructor)."""

IGNORED_ROOTS = ("hydra",)
"""Hydra's own node: its keys are Hydra's to check."""

GROUPS = {"algo": ("algo", "name"), "env": ("env", "name"), "logger": ("logger", "backend")}
"""Config group -> the config node and its entry naming the chosen option (its file's name)."""


def _option(group: str, choice: Any) -> str | None:
    """``group=choice`` if ``conf/<group>/<choice>.yaml`` exists (else the default stays)."""
    name = str(choice)
    return f"{group}={name}" if (CONF_DIR / group / f"{name}.yaml").is_file() else None


@functools.lru_cache(maxsize=64)
def _reference(overrides: tuple[str, ...]) -> DictConfig | None:
    """The default config with the given group choices (``algo=cpo``, ``+row=sac``),
    composed by Hydra without touching its global state (``None``: no config directory,
    or choices Hydra refuses: it says why itself)."""
    if not (CONF_DIR / "config.yaml").is_file():
        return None
    from hydra._internal.config_loader_impl import ConfigLoaderImpl
    from hydra._internal.utils import create_config_search_path
    from hydra.errors import HydraException
    from hydra.types import RunMode

    loader = ConfigLoaderImpl(config_search_path=create_config_search_path(f"file://{CONF_DIR}"))
    try:
        cfg = loader.load_configuration(
            config_name="config", overrides=list(overrides), run_mode=RunMode.RUN, from_shell=False
        )
    except (HydraException, ValueError):  # (omegaconf's errors are ValueErrors too)
        return None
    container = OmegaConf.to_container(cfg, resolve=False)
    container.pop("hydra", None)
    return OmegaConf.create(container)


def _paths(node: Any, prefix: str = "") -> Iterator[str]:
    """Every key path below ``node`` (nodes and leaves), not entering free-form entries."""
    if not isinstance(node, dict):
        return
    for key, value in node.items():
        path = f"{prefix}{key}"
        yield path
        if path not in FREE_FORM_KEYS:
            yield from _paths(value, f"{path}.")


def key_paths(cfg: DictConfig | dict) -> frozenset[str]:
    """Every key path of ``cfg`` (nodes and leaves, not entering free-form entries)."""
    return frozenset(_paths(_container(cfg)))


def _container(cfg: DictConfig | dict) -> dict:
    if isinstance(cfg, DictConfig):
        return OmegaConf.to_container(cfg, resolve=False)
    return dict(cfg)


def known_keys(*overrides: str) -> frozenset[str] | None:
    """Every key path of the default config composed with the group choices
    ``overrides`` (``"algo=cpo"``, ``"env=tiny"``), or ``None`` (see :func:`_reference`)."""
    reference = _reference(tuple(overrides))
    return None if reference is None else frozenset(_paths(_container(reference)))


def _choices(cfg: DictConfig | dict) -> dict[str, Any]:
    """The options ``cfg`` chose in the config groups (``{"algo": "wcsac", ...}``)."""
    cfg = cfg if isinstance(cfg, DictConfig) else OmegaConf.create(cfg)
    return {
        group: OmegaConf.select(cfg, f"{node}.{entry}", default=None)
        for group, (node, entry) in GROUPS.items()
    }


def _choice_overrides(choices: dict[str, Any]) -> tuple[str, ...]:
    return tuple(o for g, c in choices.items() if c is not None and (o := _option(g, c)))


def unknown_keys(cfg: DictConfig | dict, extra: Iterable[str] = ()) -> list[str] | None:
    """The keys of ``cfg`` that the default config of its own algorithm, env and logger
    does not have (nor ``extra``: e.g. a resumed run's saved keys); ``None`` without
    ``conf/``. A key under an unknown one is not listed again."""
    known = known_keys(*_choice_overrides(_choices(cfg)))
    return None if known is None else _outermost(_paths(_container(cfg)), known | set(extra))


def missing_keys(cfg: DictConfig | dict) -> list[str] | None:
    """The keys the default config of ``cfg``'s own algorithm, env and logger has and
    ``cfg`` lacks (a key under a missing one not listed again; not the trust flag, which
    is a command's word, never a run's); ``None`` without ``conf/``. A stored run's
    config lacking one was written by another commit's kit (:func:`~wcsac_rl.training.
    checkpoint.check_current`)."""
    reference = _reference(_choice_overrides(_choices(cfg)))
    if reference is None:
        return None
    return _outermost(_paths(_container(reference)), key_paths(cfg) | {TRUST_KEY})


def _outermost(paths: Iterable[str], skip: Collection[str]) -> list[str]:
    """The ``paths`` not in ``skip`` nor under Hydra's node, a path under one listed
    not listed again."""
    found: list[str] = []
    for path in paths:
        if path.split(".")[0] in IGNORED_ROOTS or path in skip:
            continue
        if not any(path.startswith(f"{f}.") for f in found):
            found.append(path)
    return found


def _suggestion(key: str, known: Iterable[str]) -> str:
    """`` (did you mean <the closest known setting>?)``, or nothing if none is close."""
    known = set(known)
    settings = sorted(k for k in known if not any(o.startswith(f"{k}.") for o in known))
    close = difflib.get_close_matches(key, settings, n=1, cutoff=0.6)
    return f" (did you mean {close[0]}?)" if close else ""


def _unknown_message(key: str, known: Iterable[str], where: str) -> str:
    from wcsac_rl.options import SafetyOptions  # (no torch: --help stays light)

    parts, known = key.split("."), set(known)
    if (
        len(parts) > 1
        and parts[0] == "algo"
        and parts[1] in SafetyOptions.__dataclass_fields__
        and f"algo.{parts[1]}" not in known  # (the algorithm has no safety critic)
    ):
        safe = [name for name, entry in ALGORITHMS.items() if entry.safety_critic]
        return (
            f"unknown config key {key}: an option of the safety critic and κ, which the "
            f"{where} config does not have (algo={', '.join(safe[:-1])} and {safe[-1]} do)"
        )
    return (
        f"unknown config key {key}{_suggestion(key, known)}: not a key of the {where} config "
        f"(see {CONF_DIR.name}/ for the keys)"
    )


def check_known_keys(cfg: DictConfig | dict, extra: Iterable[str] = ()) -> None:
    """Raise :class:`~wcsac_rl.training.ConfigError` (one line naming the closest known
    key) if ``cfg`` has a key its algorithm's, env's and logger's defaults lack."""
    unknown = unknown_keys(cfg, extra)
    if unknown:
        choices = _choices(cfg)
        known = known_keys(*_choice_overrides(choices)) | set(extra)
        where = " ".join(f"{g}={c}" for g, c in choices.items() if c is not None)
        raise ConfigError(_unknown_message(unknown[0], known, where))


MAX_SWEEP_REFERENCES = 64
"""A sweep over more group combinations than this is checked once composed only."""


def _group_overrides(parsed: list) -> list[list[str]]:
    """Per config-group override on a command line, its choices as override strings
    (``["algo=wcsac", "algo=cpo"]`` for a sweep ``algo=wcsac,cpo``)."""
    groups = []
    for override in parsed:
        key = override.key_or_group
        if override.is_delete() or not (CONF_DIR / key).is_dir() or key in IGNORED_ROOTS:
            continue
        prefix = "++" if override.is_force_add() else "+" if override.is_add() else ""
        values = (
            list(override.sweep_string_iterator())
            if override.is_sweep_override()
            else [override.get_value_element_as_str()]
        )
        groups.append([f"{prefix}{key}={value}" for value in values])
    return groups


def _group_options(group: str) -> list[str]:
    """What ``group=...`` may choose: the files of ``conf/<group>/`` (for ``algo``, those
    that are an algorithm or a variant of one)."""
    if group == "algo":
        from wcsac_rl.recipes import algorithm_files

        return algorithm_files(CONF_DIR)
    return sorted(p.stem for p in (CONF_DIR / group).glob("*.yaml"))


def parse_overrides(overrides: Sequence[Any]) -> list[Any] | None:
    """``overrides`` as Hydra's grammar reads them (Hydra's ``Override`` objects), or
    ``None`` where Hydra cannot parse them (its own message says why). Overrides given
    already parsed are returned as they are: a command line is parsed once, by
    :func:`~wcsac_rl.command_line.check_command_line`, for all its checks."""
    if all(not isinstance(o, str) for o in overrides):
        return list(overrides)
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    lines = [o if isinstance(o, str) else o.input_line for o in overrides]
    try:
        return OverridesParser.create().parse_overrides(lines)
    except HydraException:
        return None


def check_group_choices(overrides: Sequence[Any]) -> None:
    """Refuse a config-group choice ``conf/`` has no file for (``algo=wcsca``,
    ``env=dinamic``, each choice of a sweep) in one line naming the group's options
    (Hydra's own refusal is a block of lines with its search path); what Hydra cannot
    parse is left to it. ``overrides``: strings, or Hydra's parsed ``Override`` objects."""
    parsed = parse_overrides(overrides)
    if parsed is None:
        return
    for choices in _group_overrides(parsed):
        for choice in choices:
            group, _, name = choice.lstrip("+").partition("=")
            if group.split("/")[0] in IGNORED_ROOTS or name == "null":
                continue
            if not (CONF_DIR / group / f"{name}.yaml").is_file():
                raise ConfigError(
                    f"unknown {group} {name!r}: {CONF_DIR.name}/{group}/ has no {name}.yaml; "
                    f"choose one of {', '.join(_group_options(group))}"
                )


def _passes(override: Any, known: frozenset[str]) -> bool:
    """An override :func:`check_override_keys` leaves alone."""
    key = override.key_or_group
    return (
        override.package is not None
        or override.is_add()
        or override.is_force_add()
        or override.is_delete()
        or "/" in key
        or key.split(".")[0] in IGNORED_ROOTS
        or (CONF_DIR / key).is_dir()  # a config group (experiment=..., algo=...)
        or key in known
        or any(key.startswith(f"{free}.") for free in FREE_FORM_KEYS)
    )


def check_override_keys(overrides: Sequence[Any]) -> None:
    """Refuse a command-line override of a key that the config composed with the line's
    own group choices does not have (``algo.batchsize=64``), in one line naming the
    closest known key, before Hydra composes the config. Group choices (``algo=cpo``,
    ``+row=sac``), Hydra's keys, deletions and added keys (``+key``: checked once
    composed, by :func:`check_known_keys`) pass; what Hydra cannot parse or compose is
    left to Hydra's own message. ``overrides``: strings, or Hydra's parsed ``Override``
    objects (parsed once for all the checks)."""
    parsed = parse_overrides(overrides)
    if parsed is None:
        return
    check_group_choices(parsed)
    groups = _group_overrides(parsed)
    combos = list(itertools.islice(itertools.product(*groups), MAX_SWEEP_REFERENCES + 1))
    if len(combos) > MAX_SWEEP_REFERENCES:
        return
    references = [known_keys(*combo) for combo in combos]
    if any(ref is None for ref in references):
        return
    known = frozenset().union(*references)
    for override in parsed:
        if not _passes(override, known):
            where = " ".join(",".join(g) for g in groups) or "default"
            raise ConfigError(_unknown_message(override.key_or_group, known, where))
