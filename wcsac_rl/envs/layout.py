"""Layout sampling for the point-goal task, with Safety Gym's keepout rules.

The placement rules: docs/point_goal.md, "Placement rules". The draws of one object
are made as one vectorised batch and the first valid one is kept, which has the same
distribution as drawing them one by one. Also here: :func:`parse_explicit_layout`, the
validator of the ``reset(options={"layout": ...})`` dictionary.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

__all__ = [
    "EXPLICIT_LAYOUT_KEYS",
    "LayoutError",
    "ObjectPlacement",
    "draw_position",
    "parse_explicit_layout",
    "reset_layout",
    "sample_layout",
]

Extents = tuple[float, float, float, float]
"""Placement area as ``(xmin, ymin, xmax, ymax)``."""

EXPLICIT_LAYOUT_KEYS = ("robot_xy", "robot_heading", "goal_xy", "hazards_xy", "vases_xy")
"""Keys accepted in ``reset(options={"layout": {...}})``."""


class LayoutError(RuntimeError):
    """No layout satisfying the keepout rules was found within the allowed restarts."""


@dataclass(frozen=True)
class ObjectPlacement:
    """Placement rule of one object.

    Attributes:
        name: object name, unique within a layout (``"robot"``, ``"goal"``, ``"hazard0"`` ...).
        keepout: keepout radius; shrinks the sampling rectangle and sets the minimum
            distance ``keepout + other.keepout`` to every other object.
        fixed_xy: if given, the object always sits there (keepout checks still apply).
    """

    name: str
    keepout: float
    fixed_xy: tuple[float, float] | None = None

    def rectangle(self, extents: Extents) -> tuple[np.ndarray, np.ndarray]:
        """Low and high corners of the sampling rectangle (equal for a fixed object)."""
        if self.fixed_xy is not None:
            xy = np.asarray(self.fixed_xy, dtype=np.float64)
            return xy, xy
        xmin, ymin, xmax, ymax = extents
        k = self.keepout
        low = np.array([xmin + k, ymin + k])
        high = np.array([xmax - k, ymax - k])
        if np.any(low > high):
            raise ValueError(
                f"object {self.name!r}: keepout {k} leaves no room inside extents {extents}"
            )
        return low, high


def draw_position(
    rng: np.random.Generator,
    extents: Extents,
    obj: ObjectPlacement,
    placed_xy: np.ndarray,
    placed_keepout: np.ndarray,
    tries: int,
) -> np.ndarray | None:
    """Draw up to ``tries`` candidate positions for ``obj`` in ``extents`` and return the
    first valid one (shape ``(2,)``; ``None`` if every candidate was rejected): at least
    ``obj.keepout + placed_keepout[i]`` away from each placed object ``placed_xy[i]``.
    """
    low, high = obj.rectangle(extents)
    if obj.fixed_xy is not None:
        # Every draw from a point rectangle is the same point: one check decides.
        candidates = low[None, :]
    else:
        candidates = rng.uniform(low, high, size=(tries, 2))
    if len(placed_xy) == 0:
        return candidates[0].copy()
    diff = candidates[:, None, :] - placed_xy[None, :, :]
    dist = np.sqrt(np.sum(diff * diff, axis=-1))
    ok = np.all(dist >= obj.keepout + placed_keepout[None, :], axis=1)
    idx = np.flatnonzero(ok)
    if idx.size == 0:
        return None
    return candidates[idx[0]].copy()


def sample_layout(
    rng: np.random.Generator,
    extents: Extents,
    objects: Sequence[ObjectPlacement],
    *,
    explicit: Mapping[str, np.ndarray] | None = None,
    tries_per_object: int = 100,
    max_restarts: int = 10_000,
) -> dict[str, np.ndarray]:
    """Sample the positions of ``objects`` (placement rules, in placement order) in
    ``extents`` with the env's ``rng``: ``tries_per_object`` draws per object before the
    layout restarts, up to ``max_restarts`` times, then :class:`LayoutError`. ``explicit``
    positions are used as given, without a keepout check, and every drawn object keeps
    clear of them. Returns ``name -> xy`` (shape ``(2,)``) for every object.
    """
    explicit = dict(explicit or {})
    n = len(objects)
    keepouts = np.array([o.keepout for o in objects], dtype=np.float64)
    given = np.array([o.name in explicit for o in objects], dtype=bool)
    for _ in range(max_restarts):
        # the explicit objects are there before any draw: an object drawn earlier in the
        # order keeps clear of them too (the robot of a replayed goal and hazards)
        xy = np.zeros((n, 2))
        placed = given.copy()
        for i in np.flatnonzero(given):
            xy[i] = explicit[objects[i].name]
        failed = False
        for i, obj in enumerate(objects):
            if given[i]:
                continue
            pos = draw_position(rng, extents, obj, xy[placed], keepouts[placed], tries_per_object)
            if pos is None:
                failed = True
                break
            xy[i] = pos
            placed[i] = True
        if not failed:
            return {obj.name: xy[i].copy() for i, obj in enumerate(objects)}
    raise LayoutError(
        f"could not place {[o.name for o in objects]} in extents {extents} with keepouts "
        f"{keepouts.tolist()} after {max_restarts} layout restarts of {tries_per_object} "
        f"tries per object (explicit positions: {sorted(explicit)}); the objects do not "
        "fit: reduce their number or keepouts, or enlarge the extents"
    )


def _as_xy(value: object, what: str, count: int | None = None) -> np.ndarray:
    """``value`` as an (x, y) pair (``count=None``) or ``count`` of them, or one
    ``ValueError`` naming ``layout[what]``."""
    expected = "an (x, y) pair of numbers" if count is None else f"a list of {count} (x, y) pairs"
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise ValueError(f"layout[{what!r}] must be {expected}, got {value!r}") from err
    if count == 0 and arr.size == 0:
        return np.zeros((0, 2))
    if arr.shape != ((2,) if count is None else (count, 2)):
        got = f": {value!r}" if count is None else ""
        mine = "" if count is None else f" (this env has {count})"
        raise ValueError(f"layout[{what!r}] must be {expected}{mine}, got shape {arr.shape}{got}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"layout[{what!r}] must be finite, got {value!r}")
    return arr


def parse_explicit_layout(
    layout: object, *, hazards_num: int, vases_num: int
) -> tuple[dict[str, np.ndarray], float | None]:
    """Validate a user layout (keys :data:`EXPLICIT_LAYOUT_KEYS`, all optional: ``robot_xy``,
    ``robot_heading``, ``goal_xy``, ``hazards_num`` ``hazards_xy`` and ``vases_num``
    ``vases_xy``) and map it to object names: ``(positions, heading)``, the explicit
    objects' ``name -> xy`` and the robot heading (``None`` if not given). ``ValueError``:
    not a mapping, an unknown key, a wrong shape or count, or a non-finite value.
    """
    if not isinstance(layout, Mapping):
        raise ValueError(
            f"options['layout'] must be a dict with keys among {list(EXPLICIT_LAYOUT_KEYS)}, "
            f"got {type(layout).__name__}"
        )
    unknown = sorted(set(layout) - set(EXPLICIT_LAYOUT_KEYS))
    if unknown:
        raise ValueError(
            f"unknown layout key(s) {unknown}; valid keys are {list(EXPLICIT_LAYOUT_KEYS)}"
        )
    positions: dict[str, np.ndarray] = {}
    heading = None
    if "robot_xy" in layout:
        positions["robot"] = _as_xy(layout["robot_xy"], "robot_xy")
    if "robot_heading" in layout:
        h = layout["robot_heading"]
        try:
            heading = float(h)
        except (TypeError, ValueError) as err:
            raise ValueError(f"layout['robot_heading'] must be a number, got {h!r}") from err
        if not math.isfinite(heading):
            raise ValueError(f"layout['robot_heading'] must be finite, got {h!r}")
    if "goal_xy" in layout:
        positions["goal"] = _as_xy(layout["goal_xy"], "goal_xy")
    if "hazards_xy" in layout:
        for i, xy in enumerate(_as_xy(layout["hazards_xy"], "hazards_xy", hazards_num)):
            positions[f"hazard{i}"] = xy
    if "vases_xy" in layout:
        for i, xy in enumerate(_as_xy(layout["vases_xy"], "vases_xy", vases_num)):
            positions[f"vase{i}"] = xy
    return positions, heading


def reset_layout(
    options: object, *, hazards_num: int, vases_num: int, missing: str = ""
) -> tuple[dict[str, np.ndarray], float | None]:
    """The explicit layout ``reset(options={"layout": ...})`` gives
    (:func:`parse_explicit_layout`; none without one); ``options`` holds nothing else.
    ``missing``: the refusal of a layout naming a heading or vases (an env without them)."""
    if options is None:
        return {}, None
    if not isinstance(options, Mapping):
        raise ValueError(f"options must be a dict, got {type(options).__name__}")
    unknown = sorted(set(options) - {"layout"})
    if unknown:
        raise ValueError(f"unknown reset option(s) {unknown}; the only option is 'layout'")
    layout = options.get("layout")
    if layout is None:
        return {}, None
    if missing and isinstance(layout, Mapping) and {"robot_heading", "vases_xy"} & set(layout):
        raise ValueError(missing)
    return parse_explicit_layout(layout, hazards_num=hazards_num, vases_num=vases_num)
