"""Composite scans: several scans at known relative poses fused into one virtual scan. A
180-degree laser turned in place sees the whole room over two or three scans, door included,
which tells twin rooms apart where one scan facing a bare corner cannot.
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
    """Fuse ``scans`` (``(ranges, angles, pose)`` each, oldest first, poses in a common frame)
    into one virtual scan ``(ranges, angles)`` of ``bins`` beams over (-pi, pi] in the frame of
    the last. That newest scan is authoritative: older ones only fill the bins it left empty
    (their points carry the odometry's error); within a scan the nearest return in a bin wins.
    Older points are projected from where they were seen (occlusions are not recomputed), so
    the caller limits the travel. Raises :class:`LocalizationError` on malformed input."""
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
    # a lone hole between two returns within 5 % + 5 cm of each other gets their mean: a turned
    # scan's beams straddle bins of about their width, and a hole would split a polyline
    left, right = np.roll(out, 1), np.roll(out, -1)
    near = np.abs(left - right) <= 0.05 + 0.05 * np.minimum(left, right)
    hole = np.isnan(out) & np.isfinite(left) & np.isfinite(right) & near
    out[hole] = 0.5 * (left[hole] + right[hole])
    return out, angles
