"""Safety Gym's pseudo-lidar: a 16-bin, robot-centred proximity sensor per object class.

Object centres only, with aliasing into the neighbouring bins; each bin keeps the
maximum over objects (the rule, step by step: docs/point_goal.md, "Lidar").
"""

from __future__ import annotations

import functools
import math

import numpy as np

__all__ = ["heading_to_rotation", "pseudo_lidar", "pseudo_lidar_groups"]

_TWO_PI = 2.0 * math.pi


def heading_to_rotation(heading: float) -> np.ndarray:
    """The 2x2 rotation matrix of a robot whose +x axis points at ``heading`` (radians)."""
    c, s = math.cos(heading), math.sin(heading)
    return np.array([[c, -s], [s, c]])


def pseudo_lidar(
    points_xy: np.ndarray,
    robot_xy: np.ndarray,
    robot_rot: np.ndarray,
    num_bins: int = 16,
    max_dist: float = 3.0,
    alias: bool = True,
) -> np.ndarray:
    """Pseudo-lidar readings of one class of objects, as Safety Gym computes them:
    ``float64`` ``(num_bins,)`` values in ``[0, 1]``.

    ``points_xy``: object centres in the world frame, ``(n, 2)`` (``n`` may be 0);
    ``robot_xy``: the robot body origin; ``robot_rot``: its rotation matrix, of which the
    top-left 2x2 block (world-from-robot) is used (a MuJoCo ``xmat`` reshaped to 3x3 works);
    ``num_bins`` (at least 3) cover ``[0, 2π)``; the reading is 0 from ``max_dist`` on;
    ``alias`` also writes the aliased values into the two neighbouring bins.
    """
    points_xy = np.asarray(points_xy, dtype=np.float64).reshape(-1, 2)
    groups = np.zeros(points_xy.shape[0], dtype=np.intp)
    return pseudo_lidar_groups(
        points_xy, groups, 1, robot_xy, robot_rot, num_bins, max_dist, alias
    )[0]


def pseudo_lidar_groups(
    points_xy: np.ndarray,
    groups: np.ndarray,
    num_groups: int,
    robot_xy: np.ndarray,
    robot_rot: np.ndarray,
    num_bins: int = 16,
    max_dist: float = 3.0,
    alias: bool = True,
) -> np.ndarray:
    """Pseudo-lidar of several object classes at once (one vectorised pass): ``groups`` gives
    each object's class in ``[0, num_groups)``; the other arguments are
    :func:`pseudo_lidar`'s. Returns ``float64`` ``(num_groups, num_bins)`` whose row ``g``
    is :func:`pseudo_lidar` of the objects of class ``g``.
    """
    if num_bins < 3:
        raise ValueError(f"pseudo_lidar needs num_bins >= 3, got {num_bins}")
    n = points_xy.shape[0]
    if n == 0:
        return np.zeros((num_groups, num_bins))
    rot = np.asarray(robot_rot, dtype=np.float64)[:2, :2]
    # Robot frame: e = Rᵀ (p - robot); with row vectors that is (p - robot) @ R.
    ego = (points_xy - robot_xy[:2]) @ rot
    ex, ey = ego[:, 0], ego[:, 1]
    # angle / bin_size, with angle = atan2 mod 2π. Since angle >= 0, truncation is
    # floor; the float edge angle -> 2π (k == num_bins) is kept in the last bin.
    scaled = np.arctan2(ey, ex)
    scaled *= num_bins / _TWO_PI
    scaled %= num_bins
    k = scaled.astype(np.intp)
    np.minimum(k, num_bins - 1, out=k)
    strength = np.hypot(ex, ey)
    np.subtract(max_dist, strength, out=strength)
    np.maximum(strength, 0.0, out=strength)
    strength *= 1.0 / max_dist
    # One row per object: it writes s into bin k and, with aliasing, a*s into k+1 and
    # (1-a)*s into k-1. These three bins are distinct (num_bins >= 3), so a max over
    # rows equals Safety Gym's sequential max-update.
    weights = np.empty((n, 3))
    weights[:, 0] = 1.0
    if alias:
        np.subtract(scaled, k, out=weights[:, 1])
        np.subtract(1.0, weights[:, 1], out=weights[:, 2])
    else:
        weights[:, 1:] = 0.0
    weights *= strength[:, None]
    cols = _neighbour_table(num_bins)[k]
    cols += (groups * num_bins)[:, None]
    contrib = np.zeros((n, num_groups * num_bins))
    contrib[np.arange(n)[:, None], cols] = weights
    return contrib.max(axis=0).reshape(num_groups, num_bins)


@functools.lru_cache(maxsize=16)
def _neighbour_table(num_bins: int) -> np.ndarray:
    """Row ``k`` is ``(k, k+1, k-1) mod num_bins``."""
    k = np.arange(num_bins)
    table = np.stack([k, (k + 1) % num_bins, (k - 1) % num_bins], axis=1)
    table.flags.writeable = False
    return table
