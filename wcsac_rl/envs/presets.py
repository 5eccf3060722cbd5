"""Env presets: short names, gymnasium ids and registration.

The presets (``static``, ``dynamic``, ``point_goal1``, ``point_goal2``, ``tiny``) and
their gymnasium ids: docs/environments.md; their layouts: docs/point_goal.md, "Presets".
Importing :mod:`wcsac_rl.envs` registers the ids (idempotently). Episodes are truncated
inside the envs (1000 steps, 100 for ``tiny``), not by a ``TimeLimit`` wrapper.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

import gymnasium as gym
from gymnasium.envs.registration import load_env_creator

from wcsac_rl.envs.point_goal import PointGoalConfig

__all__ = [
    "GYM_IDS",
    "PRESETS",
    "PRESET_NAMES",
    "Preset",
    "env_title",
    "get_preset",
    "has_goals",
    "make_gym_env",
    "preset_options",
    "register_envs",
]

_POINT_GOAL_ENTRY = "wcsac_rl.envs.point_goal:PointGoalEnv"
_TINY_ENTRY = "wcsac_rl.envs.tiny:TinyHazardEnv"


@dataclass(frozen=True)
class Preset:
    """One named environment configuration: its short name in configs (``"static"``), the
    gymnasium id it is registered under, the env's ``"module:Class"`` entry point, its
    constructor's keyword arguments (``config`` for the point-goal presets) and one line
    for humans.
    """

    name: str
    gym_id: str
    entry_point: str
    kwargs: dict[str, Any] = field(default_factory=dict)
    description: str = ""

    @property
    def config(self) -> PointGoalConfig | None:
        """The :class:`PointGoalConfig` of a point-goal preset, else ``None``."""
        return self.kwargs.get("config")


STATIC_CONFIG = PointGoalConfig(
    goal_location=(1.1, 1.1),
    hazards_num=1,
    hazards_size=0.7,
    hazards_keepout=0.705,
    hazards_locations=((0.0, 0.0),),
    reward_per_step=-0.02,
)
DYNAMIC_CONFIG = PointGoalConfig()  # (PointGoalConfig's defaults are DynamicEnv's)
POINT_GOAL1_CONFIG = PointGoalConfig(
    hazards_num=8, hazards_size=0.2, hazards_keepout=0.18, vases_num=1, constrain_vases=False
)
POINT_GOAL2_CONFIG = dataclasses.replace(
    POINT_GOAL1_CONFIG,
    placement_extents=(-2.0, -2.0, 2.0, 2.0),
    hazards_num=10,
    vases_num=10,
    constrain_vases=True,
)


def _point_goal(name: str, title: str, config: PointGoalConfig, description: str) -> Preset:
    return Preset(name, f"wcsac_rl/{title}-v0", _POINT_GOAL_ENTRY, {"config": config}, description)


PRESETS: dict[str, Preset] = {
    p.name: p
    for p in (
        _point_goal(
            "static",
            "StaticEnv",
            STATIC_CONFIG,
            "WCSAC StaticEnv: fixed goal and hazard, random start, -0.02 per step",
        ),
        _point_goal(
            "dynamic",
            "DynamicEnv",
            DYNAMIC_CONFIG,
            "WCSAC DynamicEnv: random goal and 3 hazards each episode",
        ),
        _point_goal(
            "point_goal1",
            "PointGoal1",
            POINT_GOAL1_CONFIG,
            "Safety Gym PointGoal1: 8 hazards, 1 unconstrained vase",
        ),
        _point_goal(
            "point_goal2",
            "PointGoal2",
            POINT_GOAL2_CONFIG,
            "Safety Gym PointGoal2: 10 hazards, 10 constrained vases, extents ±2",
        ),
        Preset(
            "tiny",
            "wcsac_rl/TinyHazard-v0",
            _TINY_ENTRY,
            {},
            "Tiny numpy point mass to a goal past a hazard disc (smoke tests)",
        ),
    )
}
PRESET_NAMES: tuple[str, ...] = tuple(PRESETS)
"""Short names accepted by :func:`get_preset` and ``make_env``."""
GYM_IDS: dict[str, str] = {name: p.gym_id for name, p in PRESETS.items()}
"""Short name -> gymnasium id."""
_BY_GYM_ID = {p.gym_id: p for p in PRESETS.values()}


def get_preset(name: str) -> Preset:
    """Look a preset up by short name (``"dynamic"``) or gymnasium id.

    Raises:
        ValueError: unknown name; the message lists the valid ones.
    """
    if isinstance(name, str):
        if name in PRESETS:
            return PRESETS[name]
        if name in _BY_GYM_ID:
            return _BY_GYM_ID[name]
        if name.lower() in PRESETS:
            return PRESETS[name.lower()]
    raise ValueError(
        f"unknown env {name!r}; valid names are {list(PRESET_NAMES)} "
        f"(or the gymnasium ids {list(_BY_GYM_ID)})"
    )


def has_goals(name: str | None) -> bool:
    """Whether episodes of env ``name`` have a goal to reach (and a layout: hazards): the
    kit's presets do; a user's ``env=gymnasium`` env does not (its ``goal_reached`` entry
    is always False). ``None`` (no env known): as a preset."""
    if name is None:
        return True
    try:
        get_preset(name)
    except ValueError:
        return False
    return True


def env_title(name: str) -> str:
    """``"static"`` → ``"StaticEnv"`` (the gymnasium id's name), unknown names unchanged."""
    try:
        return get_preset(name).gym_id.split("/")[-1].rsplit("-v", 1)[0]
    except ValueError:
        return name


def register_envs() -> None:
    """Register every preset with gymnasium; calling it again is a no-op."""
    for preset in PRESETS.values():
        if preset.gym_id in gym.registry:
            continue
        gym.register(
            id=preset.gym_id,
            entry_point=preset.entry_point,
            kwargs=dict(preset.kwargs),
            disable_env_checker=False,
        )


def preset_options(name: str) -> frozenset[str] | None:
    """The keyword arguments a preset's env takes (``env.kwargs``): its constructor's
    and, for the point-goal presets, every :class:`PointGoalConfig` field; ``None``
    when they cannot be listed."""
    import inspect

    preset = get_preset(name)
    params = inspect.signature(load_env_creator(preset.entry_point)).parameters.values()
    names = {p.name for p in params if p.kind in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD)}
    if any(p.kind is p.VAR_KEYWORD for p in params):
        if preset.config is None:
            return None
        names |= {f.name for f in dataclasses.fields(preset.config)}
    return frozenset(names - {"config"})


def make_gym_env(name: str, *, max_episode_steps: int | None = None, **kwargs: Any) -> gym.Env:
    """The raw gymnasium env of a preset (short name or gymnasium id; no gymnasium wrappers):
    ``max_episode_steps`` overrides the episode length (the env truncates internally),
    ``kwargs`` the constructor's (``render_mode="rgb_array"``, or any
    :class:`PointGoalConfig` field of a point-goal preset, ``hazards_num=5``).
    ``ValueError``: an unknown name or keyword.
    """
    preset = get_preset(name)
    ctor_kwargs = dict(preset.kwargs)
    if max_episode_steps is not None:
        if preset.config is not None:
            ctor_kwargs["config"] = dataclasses.replace(
                preset.config, max_episode_steps=int(max_episode_steps)
            )
        else:
            ctor_kwargs["max_episode_steps"] = int(max_episode_steps)
    ctor_kwargs.update(kwargs)
    creator = load_env_creator(preset.entry_point)
    try:
        return creator(**ctor_kwargs)
    except TypeError as err:
        raise ValueError(f"bad keyword for env {preset.name!r}: {err}") from err
