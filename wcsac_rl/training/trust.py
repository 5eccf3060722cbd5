"""What a run's files may make the kit do: read values, never run code the user did not name.

A run's ``env=gymnasium env.id=module:callable`` is imported only on the user's word
(:func:`check_env_code`); a stored config with a ``${...}`` is refused
(:func:`stored_config`) and records are read unresolved (:func:`plain_select`).
The rules, per command: docs/guarantees.md ("Env code runs only on your word",
"Other files").
"""

from __future__ import annotations

import contextlib
import contextvars
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from wcsac_rl._messages import first_line
from wcsac_rl.training.errors import ConfigError

__all__ = [
    "TRUST_FLAG",
    "TRUST_KEY",
    "UntrustedEnvCode",
    "allow_env_code",
    "check_env_code",
    "check_trust",
    "env_code_allowed",
    "interpolation_in",
    "plain_select",
    "stored_config",
]

TRUST_FLAG = "--trust-env-code"
"""The flag of ``wcsac-evaluate``, ``wcsac-calibration`` and ``wcsac-report``."""
TRUST_KEY = "trust_env_code"
"""The config key (``conf/config.yaml``) of ``train.py resume=...``; never read from a run."""

USER_ENV = "gymnasium"
"""``env.name`` of a user's own env (``conf/env/gymnasium.yaml``): the one that names code."""

_ALLOWED: contextvars.ContextVar[bool] = contextvars.ContextVar(TRUST_KEY, default=False)


class UntrustedEnvCode(ConfigError):
    """A run's files name env code the user did not allow (the message says how to)."""


@contextlib.contextmanager
def allow_env_code(allowed: bool = True) -> Iterator[None]:
    """Within the block, runs whose files name env code may import it (what a command's
    :data:`TRUST_FLAG` does for everything the command loads, e.g. a report's figures)."""
    token = _ALLOWED.set(bool(allowed))
    try:
        yield
    finally:
        _ALLOWED.reset(token)


def env_code_allowed() -> bool:
    """Whether the current command allowed env code (:func:`allow_env_code`)."""
    return _ALLOWED.get()


def _walk(node: Any, prefix: str = "") -> Iterator[tuple[str, Any]]:
    if isinstance(node, Mapping):
        for key, value in node.items():
            yield from _walk(value, f"{prefix}{key}.")
    elif isinstance(node, (list, tuple)):
        for i, value in enumerate(node):
            yield from _walk(value, f"{prefix}{i}.")
    else:
        yield prefix[:-1], node


def interpolation_in(data: Any) -> tuple[str, str] | None:
    """The first ``(key, value)`` of ``data`` (a plain container) whose string value holds
    an OmegaConf interpolation ``${...}``; ``None`` when there is none."""
    for key, value in _walk(data):
        if isinstance(value, str) and "${" in value:
            return key, value
    return None


def stored_config(data: Any, source: str | Path) -> DictConfig:
    """A run's stored config (a checkpoint's ``config`` entry, a ``config.yaml``) as a
    :class:`~omegaconf.DictConfig`, after checking that it is a mapping of resolved
    values: a ``${...}`` in it is refused (one line naming the key), never resolved."""
    if isinstance(data, DictConfig):
        data = OmegaConf.to_container(data, resolve=False)
    if not isinstance(data, dict) or not all(isinstance(k, str) for k in data):
        raise ConfigError(
            f"{source}: its config is not a mapping of settings (got {type(data).__name__})"
        )
    found = interpolation_in(data)
    if found is not None:
        key, value = found
        raise ConfigError(
            f"{source}: its config holds an interpolation at {key} ({value!r}); a run's "
            "stored config holds resolved values, and wcsac_rl resolves none read from a "
            "run's files"
        )
    try:
        return OmegaConf.create(data)
    except Exception as err:  # (omegaconf's errors: a key or value it cannot hold)
        raise ConfigError(f"{source}: its config cannot be read ({first_line(err)})") from None


def plain_select(data: Any, key: str) -> Any:
    """``data``'s value at the dotted ``key`` (``None`` when absent), read without
    resolving anything: from a :class:`~omegaconf.DictConfig` its raw container."""
    if isinstance(data, DictConfig):
        data = OmegaConf.to_container(data, resolve=False)
    for part in key.split("."):
        if not isinstance(data, Mapping) or part not in data:
            return None
        data = data[part]
    return data


def _named_code(cfg: Any) -> str | None:
    """The ``env.id`` a config's env would import and call (``None``: a built-in env)."""
    if plain_select(cfg, "env.name") != USER_ENV:
        return None
    env_id = plain_select(cfg, "env.id")
    return env_id if isinstance(env_id, str) else repr(env_id)


def check_trust(value: Any, name: str = TRUST_KEY) -> bool:
    """``value`` if it is a bool, else one :class:`~wcsac_rl.training.ConfigError` line:
    trust is given only by ``True`` (a string such as ``"false"`` read from an
    environment variable would otherwise count as trust)."""
    if not isinstance(value, bool):
        raise ConfigError(
            f"{name} must be True or False (a bool), got {value!r} "
            f"({type(value).__name__}); only True trusts a run's code"
        )
    return value


def check_env_code(
    cfg: Any, source: str | Path, *, trusted: bool, given_id: str | None = None, allow: str
) -> None:
    """Refuse, with :class:`UntrustedEnvCode`, to build the env of a config read from a
    run's files (``source``) when that env is code (``env=gymnasium``) the user has not
    allowed: by ``trusted`` (the command's flag; :func:`allow_env_code` counts too) or
    by naming the same ``env.id`` on this command's line (``given_id``). ``allow`` says
    how to allow it (the flag of the command). Nothing is imported here."""
    check_trust(trusted)
    env_id = _named_code(cfg)
    if env_id is None or trusted or env_code_allowed() or given_id == env_id:
        return
    module, sep, _ = env_id.partition(":")
    what = (
        f"imports the module {module!r} and calls it with env.kwargs"
        if sep
        else "builds that registered gymnasium env with env.kwargs"
    )
    raise UntrustedEnvCode(
        f"{source}: the run's config names code to run (env.id={env_id} {what}); nothing "
        f"was imported. If you trust this run's code, {allow}"
    )
