"""The paper's two comparison methods (section 6): grid-based ICP and line matching.

Both are *tracking* methods: they refine the previous estimate by local optimisation and
therefore need a start pose (no global localisation). Shared helpers for input checking and the
closed-form 2D rigid least-squares fit live here.
"""

from __future__ import annotations

import numpy as np

from schemas.errors import LocalizationError
from service.core.types import wrap_angle

__all__ = [
    "check_odom",
    "check_pose",
    "compose",
    "relative",
    "rigid_fit",
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


def transform_points(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Map ``(n, 2)`` robot-frame points to the map frame with ``pose = [x, y, theta]``."""
    c, s = np.cos(pose[2]), np.sin(pose[2])
    x = points[:, 0] * c - points[:, 1] * s + pose[0]
    y = points[:, 0] * s + points[:, 1] * c + pose[1]
    return np.column_stack([x, y])


def rigid_fit(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Closed-form weighted least-squares rigid transform with ``dst ~ R(theta) src + t``.

    ``src`` are robot-frame points and ``dst`` their map-frame partners (both ``(n, 2)``,
    n >= 2, metres). Returns the pose ``[tx, ty, theta]`` that, applied to ``src``, minimises
    the weighted squared distances.
    """
    w = np.ones(len(src)) if weights is None else np.asarray(weights, dtype=np.float64)
    sw = float(w.sum())
    if len(src) < 2 or sw <= 0.0:
        raise LocalizationError("rigid fit needs at least two weighted point pairs")
    ps = (w @ src) / sw
    pd = (w @ dst) / sw
    a = src - ps
    b = dst - pd
    sxx = float(w @ (a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1]))
    sxy = float(w @ (a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]))
    theta = float(np.arctan2(sxy, sxx))
    c, s = np.cos(theta), np.sin(theta)
    tx = pd[0] - (c * ps[0] - s * ps[1])
    ty = pd[1] - (s * ps[0] + c * ps[1])
    return np.array([tx, ty, wrap_angle(theta)], dtype=np.float64)


def compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pose composition ``a (+) b``: ``b`` expressed in the frame of ``a``."""
    c, s = np.cos(a[2]), np.sin(a[2])
    return np.array(
        [a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], wrap_angle(a[2] + b[2])],
        dtype=np.float64,
    )


def relative(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The increment ``d`` with ``a (+) d = b``: pose ``b`` expressed in the frame of ``a``."""
    c, s = np.cos(a[2]), np.sin(a[2])
    dx, dy = b[0] - a[0], b[1] - a[1]
    return np.array([c * dx + s * dy, -s * dx + c * dy, wrap_angle(b[2] - a[2])], dtype=np.float64)


def check_odom(odom: np.ndarray | None) -> np.ndarray | None:
    """Validate an optional odometry pose ``[x, y, theta]`` (odometry frame)."""
    if odom is None:
        return None
    o = np.asarray(odom, dtype=np.float64).reshape(-1)
    if o.shape != (3,) or not np.all(np.isfinite(o)):
        raise LocalizationError(f"odom must be 3 finite numbers [x, y, theta], got {o.shape}")
    return o
