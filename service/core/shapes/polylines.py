"""Grouping of range readings into polylines (paper §4.1, first step of shape extraction).

A range scan is an angularly ordered sequence of returns. Consecutive returns that lie close
to each other are assumed to belong to the same object and are joined into one polygonal
line (*polyline*); a missing return or a jump larger than the grouping threshold starts a new
polyline. The resulting list keeps the angular (cyclic) order of the scan, which the
configuration matching (§4.2, §5.2) uses as a hard constraint.

Frames: points are expressed in the sensor's frame (the robot frame for a real scan, the
viewpoint's frame for a map's virtual scan); the sensor sits at the origin and beam ``i``
points at ``angles[i]`` radians (counter-clockwise from the frame's x axis). Units: metres.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from service.core import kernels, numeric
from service.core.kernels import extract as extract_kernels
from service.errors import LocalizationError

#: Minimum object distance assumed by the paper (§4.1): 10 cm.
MIN_OBJECT_DISTANCE = 0.10

#: Factor ``c`` of the range-adaptive grouping threshold ``c * r * dtheta``.
#:
#: Two consecutive returns of a straight wall seen at incidence angle ``beta`` (angle between
#: beam and wall) at range ``r`` are about ``r * dtheta / sin(beta)`` apart. With ``c = 4``
#: a wall stays in one piece down to ``beta = asin(1/4) ~ 14.5 deg``; below that the returns
#: are so sparse that the wall carries hardly any shape information anyway. At 0.5 deg
#: resolution the threshold is 10 cm up to ~2.9 m and 35 cm at 10 m, so a depth jump of more
#: than a third of a metre at 10 m still separates two objects.
RANGE_FACTOR = 4.0


@dataclass(frozen=True, eq=False)
class Polyline:
    """One group of consecutive returns, in angular order (compared and hashed by identity).

    ``points`` ``(k, 2)`` float64 metres in the sensor frame; ``idx`` ``(k,)`` int beam indices
    of the points (strictly increasing, except for a polyline joined across the wrap-around of a
    360-degree scan, where the indices continue from ``n - 1`` to ``0``); ``first_beam`` /
    ``last_beam`` the beam indices of the first / last point; ``bearing_start`` /
    ``bearing_end`` radians, the bearing of the first / last point as seen from the origin.
    """

    points: np.ndarray
    idx: np.ndarray
    first_beam: int
    last_beam: int
    bearing_start: float
    bearing_end: float

    @cached_property
    def length(self) -> float:
        """Length along the polyline in metres (sum of edge lengths)."""
        d = np.diff(self.points, axis=0)
        return float(np.sum(np.hypot(d[:, 0], d[:, 1])))

    @cached_property
    def angular_size(self) -> float:
        """Angle (radians, >= 0) the polyline subtends as seen from the sensor origin.

        Computed as the absolute sum of the wrapped bearing steps between consecutive points,
        so it is correct across the -pi/pi seam and for polylines wider than pi.
        """
        b = numeric.atan2(self.points[:, 1], self.points[:, 0])
        steps = np.diff(b)
        steps = (steps + np.pi) % (2.0 * np.pi) - np.pi
        return float(abs(np.sum(steps)))

    def __len__(self) -> int:
        return int(self.points.shape[0])

    def subset(self, keep: np.ndarray) -> Polyline:
        """The polyline restricted to the point positions ``keep`` (e.g. DCE-kept indices).

        ``keep`` indexes ``points`` (not beams) and must contain the first and last position.
        """
        keep = np.asarray(keep, dtype=np.intp)
        if keep.size < 2 or keep[0] != 0 or keep[-1] != len(self) - 1:
            raise LocalizationError("subset must keep the first and the last point")
        pts = self.points[keep]
        pts.setflags(write=False)
        ids = self.idx[keep]
        ids.setflags(write=False)
        return Polyline(
            points=pts,
            idx=ids,
            first_beam=self.first_beam,
            last_beam=self.last_beam,
            bearing_start=self.bearing_start,
            bearing_end=self.bearing_end,
        )


def _check_scan(ranges: np.ndarray, angles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    r = np.asarray(ranges, dtype=np.float64)
    a = np.asarray(angles, dtype=np.float64)
    if r.ndim != 1 or a.ndim != 1 or r.shape != a.shape:
        raise LocalizationError(
            f"ranges and angles must be 1-D of equal length, got {r.shape} and {a.shape}"
        )
    if not np.isfinite(a).all():
        raise LocalizationError("beam angles must be finite")
    if (r < 0.0).any() or np.isinf(r).any():  # NaN < 0 is false
        raise LocalizationError("ranges must be >= 0 or NaN (no return); got negative or inf")
    return r, a


def scan_to_points(ranges: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """Cartesian points ``(n, 2)`` (metres, sensor frame) of a scan.

    ``ranges`` metres with NaN for "no return", ``angles`` radians in the sensor frame; rows of
    missing returns are NaN. Raises :class:`LocalizationError` on mismatched shapes.
    """
    r, a = _check_scan(ranges, angles)
    return np.column_stack((r * np.cos(a), r * np.sin(a)))


def _make(pts: np.ndarray, ids: np.ndarray) -> Polyline:
    pts = np.ascontiguousarray(pts, dtype=np.float64)
    ids = np.ascontiguousarray(ids, dtype=np.intp)
    pts.setflags(write=False)
    ids.setflags(write=False)
    return Polyline(
        points=pts,
        idx=ids,
        first_beam=int(ids[0]),
        last_beam=int(ids[-1]),
        bearing_start=math.atan2(pts[0, 1], pts[0, 0]),
        bearing_end=math.atan2(pts[-1, 1], pts[-1, 0]),
    )


def group_polylines(
    ranges: np.ndarray,
    angles: np.ndarray,
    min_object_distance: float = MIN_OBJECT_DISTANCE,
    range_factor: float = RANGE_FACTOR,
    min_points: int = 2,
    wrap: bool = False,
) -> list[Polyline]:
    """Group a scan into polylines (paper §4.1, "grouping").

    Consecutive valid returns ``i`` and ``i + 1`` are joined while their Euclidean distance is
    below ``max(min_object_distance, range_factor * min(r_i, r_{i+1}) * |dtheta_i|)``: the
    paper's assumed minimum object distance of 10 cm, widened with range and angular step so a
    wall seen at a grazing angle is not shredded (see :data:`RANGE_FACTOR` for the choice of
    ``c = 4``). A NaN range (no return) always splits. Groups with fewer than ``min_points``
    points are dropped (isolated returns carry no shape).

    ``wrap=True`` is for 360-degree (virtual) scans whose last beam neighbours the first: if
    the last and the first beam both hold returns that pass the same test, the last group and
    the first group are joined into one polyline. That polyline is put LAST in the list (it
    starts at the highest beam index), so the list stays in cyclic beam order.

    Returns the polylines in beam (angular) order. ``ranges`` metres (NaN = no return),
    ``angles`` radians in the sensor frame, both ``(n,)``. Raises :class:`LocalizationError`
    on malformed input.
    """
    r, a = _check_scan(ranges, angles)
    n = r.shape[0]
    if n == 0:
        return []
    if min_points < 1:
        raise LocalizationError(f"min_points must be >= 1, got {min_points}")
    pts = np.column_stack((r * np.cos(a), r * np.sin(a)))
    valid = ~np.isnan(r)

    def joined(i: np.ndarray, j: np.ndarray) -> np.ndarray:
        dth = np.abs((a[j] - a[i] + np.pi) % (2.0 * np.pi) - np.pi)
        thr = np.maximum(min_object_distance, range_factor * np.fmin(r[i], r[j]) * dth)
        d = np.hypot(pts[j, 0] - pts[i, 0], pts[j, 1] - pts[i, 1])
        return valid[i] & valid[j] & (d < thr)

    if n > 1:
        i = np.arange(n - 1)
        link = joined(i, i + 1)
    else:
        link = np.zeros(0, dtype=bool)
    # Group starts: valid points not linked to their predecessor; ends: not linked onwards.
    linked_prev = np.concatenate(([False], link))
    linked_next = np.concatenate((link, [False]))
    starts = np.flatnonzero(valid & ~linked_prev).tolist()
    ends = np.flatnonzero(valid & ~linked_next).tolist()
    groups: list[tuple[int, int]] = list(zip(starts, ends, strict=True))  # inclusive

    wrapped: tuple[np.ndarray, np.ndarray] | None = None
    if (
        wrap
        and n > 2
        and len(groups) >= 2
        and groups[0][0] == 0
        and groups[-1][1] == n - 1
        and bool(joined(np.array([n - 1]), np.array([0]))[0])
    ):
        (s0, e0), (s1, e1) = groups[0], groups[-1]
        ids = np.concatenate((np.arange(s1, e1 + 1), np.arange(s0, e0 + 1)))
        wrapped = (pts[ids], ids)
        groups = groups[1:-1]

    out = [_make(pts[s : e + 1], np.arange(s, e + 1)) for s, e in groups if e - s + 1 >= min_points]
    if wrapped is not None and wrapped[1].shape[0] >= min_points:
        out.append(_make(*wrapped))
    return out


def group_spans(
    ranges: np.ndarray,
    angles: np.ndarray,
    min_object_distance: float = MIN_OBJECT_DISTANCE,
    range_factor: float = RANGE_FACTOR,
    min_points: int = 2,
    min_length: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """The grouping of :func:`group_polylines` (no wrap-around) as index spans, for a scan
    that may never need its polylines as objects (a tracked scan whose prior fits).

    Returns ``(points, spans)``: ``points`` ``(n, 2)`` of every beam (sensor frame, NaN rows
    for no return), ``spans`` ``(k, 2)`` the first and last beam (inclusive) of each group of
    at least ``min_points`` points and ``min_length`` metres, in beam order
    (:func:`polylines_of_spans` makes them polylines). One compiled pass when numba is there;
    :func:`group_polylines` is the reference. Raises :class:`LocalizationError` on malformed
    input.
    """
    r, a = _check_scan(ranges, angles)
    if min_points < 1:
        raise LocalizationError(f"min_points must be >= 1, got {min_points}")
    pts = np.column_stack((r * np.cos(a), r * np.sin(a)))
    if kernels.HAVE_NUMBA:
        spans = extract_kernels.group_spans(
            r,
            a,
            pts,
            float(min_object_distance),
            float(range_factor),
            int(min_points),
            float(min_length),
        )
    else:
        groups = group_polylines(r, a, min_object_distance, range_factor, min_points)
        spans = np.array(
            [(g.first_beam, g.last_beam) for g in groups if g.length >= min_length],
            dtype=np.intp,
        ).reshape(-1, 2)
    return pts, spans


def polylines_of_spans(points: np.ndarray, spans: np.ndarray) -> list[Polyline]:
    """The polylines of :func:`group_spans`' ``(points, spans)``, in beam order."""
    return [_make(points[s : e + 1], np.arange(s, e + 1)) for s, e in spans.tolist()]
