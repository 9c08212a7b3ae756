"""The paper's two comparison methods (section 6): grid-based ICP and line matching.

Both are *tracking* methods: they refine the previous estimate by local optimisation and
therefore need a start pose (no global localisation). Their shared input checks live here; the
pose algebra (``compose``, ``relative``, ``transform_points``) is re-exported from
:mod:`service.core.pose`, the one place for it.
"""

from __future__ import annotations

import numpy as np

from service.core.pose import compose, relative, transform_points
from service.core.types import wrap_angle
from service.errors import LocalizationError

__all__ = [
    "check_odom",
    "check_pose",
    "compose",
    "relative",
    "scan_points",
    "transform_points",
]


def check_pose(pose: np.ndarray | None, method: str) -> np.ndarray:
    """Validate a start pose ``[x m, y m, theta rad]`` (map frame) and return a float64 copy.

    Raises :class:`LocalizationError` for ``None`` (these methods cannot localise globally) and
    for a wrong shape or non-finite values.
    """
    if pose is None:
        raise LocalizationError(
            f"method {method!r} is a tracking method and needs an initial pose; it cannot do "
            "global localisation (use method 'shape' for an unknown start pose)"
        )
    p = np.asarray(pose, dtype=np.float64).reshape(-1)
    if p.shape != (3,):
        raise LocalizationError(f"initial pose must be [x, y, theta], got shape {p.shape}")
    if not np.all(np.isfinite(p)):
        raise LocalizationError("initial pose has a non-finite component")
    return np.array([p[0], p[1], wrap_angle(p[2])], dtype=np.float64)


def scan_points(ranges: np.ndarray, angles: np.ndarray, range_max: float = np.inf) -> np.ndarray:
    """Convert one scan to ``(n, 2)`` points in the robot frame (metres, x forward, y left).

    ``ranges`` (metres, NaN = no return) and ``angles`` (radians, robot frame) must be 1-D of
    equal length with finite angles. Non-positive, NaN, infinite or ``> range_max`` ranges are
    dropped; the beam order is kept.
    """
    r = np.asarray(ranges, dtype=np.float64)
    a = np.asarray(angles, dtype=np.float64)
    if r.ndim != 1 or a.ndim != 1:
        raise LocalizationError(f"ranges and angles must be 1-D, got {r.shape} and {a.shape}")
    if r.shape != a.shape:
        raise LocalizationError(f"ranges ({r.size}) and angles ({a.size}) differ in length")
    if not np.all(np.isfinite(a)):
        raise LocalizationError("angles contain a non-finite value")
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(r) & (r > 0.0) & (r <= range_max)
    rr, aa = r[ok], a[ok]
    return np.column_stack([rr * np.cos(aa), rr * np.sin(aa)])


def check_odom(odom: np.ndarray | None) -> np.ndarray | None:
    """Validate an optional odometry pose ``[x, y, theta]`` (odometry frame)."""
    if odom is None:
        return None
    o = np.asarray(odom, dtype=np.float64).reshape(-1)
    if o.shape != (3,) or not np.all(np.isfinite(o)):
        raise LocalizationError(f"odom must be 3 finite numbers [x, y, theta], got {o.shape}")
    return o
