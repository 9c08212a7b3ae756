"""The laser's mounting on the robot: any localiser estimates the laser's pose, its users speak
the robot base's.

Frames (REP 103; poses ``[x, y, theta]``, metres and radians, theta counter-clockwise). The
mounting ``m`` is the laser's pose in the base frame (``x`` forward, ``y`` left). With ``⊕``
the pose composition:

* laser pose from the base pose: ``l = b ⊕ m``; base pose from the laser pose:
  ``b = l ⊕ m⁻¹``;
* odometry: the base's odometry pose ``o`` becomes the laser's, ``o ⊕ m`` (same odometry
  frame; its increments are the laser's motion, which is what a localiser of the laser needs);
* covariance: ``Σ_b = J Σ_l Jᵀ`` with ``J = ∂b/∂l``, the identity but for the heading column
  ``[-(b_y - l_y), b_x - l_x, 1]`` (a turn of the laser swings the base around it).

:class:`MountedLocalizer` wraps a localiser of any method with these: odometry and initial
poses in (the base's) are turned into the laser's, estimates out (the pose, its covariance
and a global search's candidates) into the base's; the localiser inside works exactly as
without a mounting. :func:`mount` returns the localiser itself for a zero (or absent)
mounting, so poses are bit for bit what they were before mountings existed.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from service.core.types import Estimate, Localizer, LocalizerWrapper, wrap_angle
from service.errors import LocalizationError

__all__ = [
    "MountedLocalizer",
    "base_covariance",
    "check_offset",
    "mount",
    "to_base",
    "to_laser",
]


def check_offset(offset: Sequence[float] | np.ndarray) -> np.ndarray:
    """``offset`` as a read-only float64 ``(3,)`` array with finite values (heading wrapped to
    (-pi, pi]), or :class:`LocalizationError`."""
    m = np.asarray(offset, dtype=np.float64).reshape(-1)
    if m.shape != (3,) or not np.all(np.isfinite(m)):
        raise LocalizationError(f"laser offset must be 3 finite numbers [x, y, theta], got {m}")
    out = np.array([m[0], m[1], wrap_angle(float(m[2]))], dtype=np.float64)
    out.setflags(write=False)
    return out


def _compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a ⊕ b`` for poses ``(..., 3)`` ``a`` and one pose ``(3,)`` ``b``."""
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    out = np.empty(np.broadcast_shapes(a.shape, (3,)), dtype=np.float64)
    out[..., 0] = a[..., 0] + c * b[0] - s * b[1]
    out[..., 1] = a[..., 1] + s * b[0] + c * b[1]
    out[..., 2] = wrap_angle(a[..., 2] + b[2])
    return out


def _inverse(m: np.ndarray) -> np.ndarray:
    c, s = math.cos(m[2]), math.sin(m[2])
    return np.array([-c * m[0] - s * m[1], s * m[0] - c * m[1], -m[2]], dtype=np.float64)


def to_laser(base: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """Laser poses ``(..., 3)`` of base poses ``(..., 3)`` (map or odometry frame)."""
    return _compose(np.asarray(base, dtype=np.float64), np.asarray(offset, dtype=np.float64))


def to_base(laser: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """Base poses ``(..., 3)`` of laser poses ``(..., 3)``."""
    return _compose(np.asarray(laser, dtype=np.float64), _inverse(np.asarray(offset)))


def base_covariance(laser: np.ndarray, cov: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """The 3x3 covariance of the base pose given that of the laser pose ``laser`` (module
    docstring: the Jacobian of ``b = l ⊕ m⁻¹`` with respect to ``l``)."""
    lp = np.asarray(laser, dtype=np.float64).reshape(3)
    b = to_base(lp, offset)
    J = np.eye(3)
    J[0, 2] = -(b[1] - lp[1])
    J[1, 2] = b[0] - lp[0]
    return J @ np.asarray(cov, dtype=np.float64).reshape(3, 3) @ J.T


class MountedLocalizer(LocalizerWrapper):
    """A localiser of the laser's pose seen as one of the base's pose (module docstring).

    ``update`` takes the scan (laser frame, unchanged) and the base's odometry; ``reset``
    takes the base's initial pose and odometry; :attr:`pose` and every :class:`Estimate` are
    the base's. Everything else (``method``, ``unsettled``, ``set_search_budget``, ...) is the
    wrapped localiser's; ``map_data`` is read and set on it. Picklable (a worker hands it to
    another) when the wrapped localiser is.
    """

    def __init__(self, inner: Localizer, offset: Sequence[float] | np.ndarray) -> None:
        super().__init__(inner)
        self.offset = check_offset(offset)

    @property
    def pose(self) -> np.ndarray | None:
        """Last estimate of the base's pose, or ``None`` before the first fix."""
        p = self.inner.pose
        return None if p is None else to_base(np.asarray(p, dtype=np.float64), self.offset)

    def _laser_odom(self, odom: np.ndarray | None) -> np.ndarray | None:
        return None if odom is None else to_laser(np.asarray(odom, dtype=np.float64), self.offset)

    def update(
        self, ranges: np.ndarray, angles: np.ndarray, odom: np.ndarray | None = None
    ) -> Estimate:
        """Localise one scan (laser frame) with the base's odometry pose ``odom``; the
        estimate is the base's."""
        est = self.inner.update(ranges, angles, self._laser_odom(odom))
        return self.base_estimate(est)

    def reset(self, initial_pose: np.ndarray | None, odom: np.ndarray | None = None) -> None:
        """Restart from the base's pose ``initial_pose`` (``None``: global localisation) with
        the base's odometry pose ``odom`` there."""
        start = None
        if initial_pose is not None:
            start = to_laser(np.asarray(initial_pose, dtype=np.float64), self.offset)
        self.inner.reset(start, self._laser_odom(odom))

    def base_estimate(self, est: Estimate) -> Estimate:
        """``est`` (the laser's) with its pose, covariance and candidates the base's."""
        laser = np.asarray(est.pose, dtype=np.float64).reshape(3)
        changes: dict[str, Any] = {"pose": to_base(laser, self.offset)}
        if est.covariance is not None:
            changes["covariance"] = base_covariance(laser, est.covariance, self.offset)
        if est.candidates is not None:
            c = np.array(est.candidates, dtype=np.float64).reshape(-1, 4)
            if c.shape[0]:
                c[:, :3] = to_base(c[:, :3], self.offset)
            changes["candidates"] = c
        return dataclasses.replace(est, **changes)


def mount(loc: Localizer, offset: Sequence[float] | np.ndarray | None) -> Localizer:
    """``loc`` seen from the robot base when the laser sits at ``offset`` on it; ``loc``
    itself when ``offset`` is ``None`` or zero (no arithmetic at all on the poses)."""
    if offset is None:
        return loc
    m = check_offset(offset)
    if not np.any(m):
        return loc
    return MountedLocalizer(loc, m)  # type: ignore[return-value]
