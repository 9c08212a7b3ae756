"""Composite scans: several scans at known relative poses fused into one virtual scan.

A robot that does not know where it is can look around: a 180-degree laser turned in place
sees the whole room over two or three scans, with the door, which tells twin rooms apart
where a single scan facing a bare corner cannot. The global search
(:mod:`service.core.reloc.global_localization`) therefore fuses the scans of its search window into
one virtual 360-degree scan from the newest pose, using the odometry sent with the scans for
the relative poses, and matches that against the map's abstract sensor readings, which are
360-degree views too.

Choices (named here, used by the global search):

- The virtual scan has ``bins`` beams evenly over (-pi, pi] (bin centres), robot frame of the
  newest scan, REP 103 (x forward, y left, angles CCW). A bin with no return is NaN.
- The newest scan is authoritative: a bin it has a return in keeps that return. Older scans
  only fill bins the newer ones left empty (behind the robot, outside the newer fields of
  view). Their points carry the odometry error of the turn, the newest scan's do not.
- Within one scan, several returns falling into one bin keep the nearest (occlusion).
- A lone empty bin between two nearly equal returns is filled with their mean: a turned
  scan's beams straddle bins of about their own width, and a hole would split a polyline.
- Older points are projected from where they were seen: after a translation the virtual
  scan is only an approximation of what the newest pose would see (occlusions are not
  recomputed), so callers limit the travel (:data:`service.core.reloc.states.COMPOSITE_TRAVEL`).

Pure numpy; units metres and radians.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from service.core import numeric
from service.core.pose import compose, invert, transform_points
from service.errors import LocalizationError


def composite_scan(
    scans: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]], bins: int = 720
) -> tuple[np.ndarray, np.ndarray]:
    """Fuse ``scans`` — ``(ranges, angles, pose)`` each, oldest first, ``pose`` ``[x, y,
    theta]`` in any common frame (odometry) — into one virtual scan ``(ranges, angles)`` of
    ``bins`` beams over (-pi, pi] in the frame of the LAST scan's pose (module docstring).
    Raises :class:`LocalizationError` on an empty list, ``bins < 8`` or malformed arrays."""
    if not scans:
        raise LocalizationError("composite_scan needs at least one scan")
    if bins < 8:
        raise LocalizationError(f"bins must be >= 8, got {bins}")
    width = 2.0 * np.pi / bins
    angles = -np.pi + (np.arange(bins) + 0.5) * width
    out = np.full(bins, np.nan)
    checked = []
    for ranges, beam_angles, pose in scans:
        r = np.asarray(ranges, dtype=np.float64)
        a = np.asarray(beam_angles, dtype=np.float64)
        p = np.asarray(pose, dtype=np.float64)
        if r.ndim != 1 or r.shape != a.shape or p.shape != (3,) or not np.all(np.isfinite(p)):
            raise LocalizationError(
                f"composite_scan: ranges {r.shape}, angles {a.shape}, pose {p.shape} "
                "(expected equal 1-D ranges and angles and a finite [x, y, theta])"
            )
        checked.append((r, a, p))
    to_last = invert(checked[-1][2])
    for r, a, p in reversed(checked):  # newest first: it claims its bins
        ok = np.isfinite(r) & np.isfinite(a)
        if not np.any(ok):
            continue
        xy = np.column_stack([r[ok] * np.cos(a[ok]), r[ok] * np.sin(a[ok])])
        q = transform_points(compose(to_last, p), xy)
        rng = np.hypot(q[:, 0], q[:, 1])
        b = np.floor((numeric.atan2(q[:, 1], q[:, 0]) + np.pi) / width).astype(np.int64) % bins
        nearest = np.full(bins, np.inf)
        np.minimum.at(nearest, b, rng)
        free = np.isnan(out) & np.isfinite(nearest)
        out[free] = nearest[free]
    return _fill_single_gaps(out), angles


def _fill_single_gaps(r: np.ndarray) -> np.ndarray:
    """A lone empty bin between two returns within 5 % + 5 cm of each other gets their mean
    (module docstring; cyclically: the first and last bins are neighbours)."""
    left = np.roll(r, 1)
    right = np.roll(r, -1)
    near = np.abs(left - right) <= 0.05 + 0.05 * np.minimum(left, right)
    hole = np.isnan(r) & np.isfinite(left) & np.isfinite(right) & near
    out = r.copy()
    out[hole] = 0.5 * (left[hole] + right[hole])
    return out
