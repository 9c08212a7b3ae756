"""Compiled inner loops of exact ray casting (implementation details, numba; the conventions
of :mod:`service.core.kernels`: the arithmetic follows the numpy reference expression by
expression, no ``fastmath``).

:meth:`service.core.sensor.raycast.RayCaster.cast_many` keeps the segments near each pose, turns
each into the run of beams (in bearing order) its bearing interval covers, and tests every
(beam, segment) pair of those runs exactly. The numpy reference builds all of that as arrays;
these kernels do the same steps in loops, without the temporaries:

- :func:`near_segments`: the distance test, and the near segments' data compacted;
- the bearings' ``arctan2`` stay in numpy (numba's ``atan2`` differs from numpy's in the last
  bit for a few per cent of inputs; every other operation here gives numpy's bits);
- :func:`nearest_hits`: the bearing intervals, their beam runs (binary search, numpy's
  ``searchsorted`` sides) and the exact test, keeping the nearest range per beam.

So every range has the reference's bits (tests compare both).
"""

from __future__ import annotations

import math

import numpy as np

from service.core.kernels import njit

_TWO_PI = 2.0 * math.pi


@njit(cache=True, nogil=True)
def near_segments(
    a: np.ndarray, e: np.ndarray, ee: np.ndarray, poses: np.ndarray, max_range: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per pose (in order) the segments whose distance to the sensor is within
    ``max_range``: their index, their pose and whether they touch the sensor (distance
    <= 1e-12), as :meth:`service.core.sensor.raycast.RayCaster._distances` computes the distance;
    and the vectors from the sensor to each one's start and end, ``[ax - px,
    ay - py, (ax + ex) - px, (ay + ey) - py]`` (the ``arctan2`` arguments of the bearings,
    the reference's operations in its order), as ``(4, m)`` (each row contiguous, as the
    reference's arrays are)."""
    n_pose = poses.shape[0]
    n_seg = a.shape[0]
    idx = np.empty(n_pose * n_seg, dtype=np.intp)
    owner = np.empty(n_pose * n_seg, dtype=np.intp)
    touching = np.empty(n_pose * n_seg, dtype=np.bool_)
    ends = np.empty((4, n_pose * n_seg))
    m = 0
    for k in range(n_pose):
        x = poses[k, 0]
        y = poses[k, 1]
        for j in range(n_seg):
            apx = x - a[j, 0]
            apy = y - a[j, 1]
            t = (apx * e[j, 0] + apy * e[j, 1]) / ee[j]
            t = min(max(t, 0.0), 1.0)
            d = math.hypot(apx - t * e[j, 0], apy - t * e[j, 1])
            if d <= max_range:
                idx[m] = j
                owner[m] = k
                touching[m] = d <= 1e-12
                ends[0, m] = a[j, 0] - x
                ends[1, m] = a[j, 1] - y
                ends[2, m] = (a[j, 0] + e[j, 0]) - x
                ends[3, m] = (a[j, 1] + e[j, 1]) - y
                m += 1
    return idx[:m], owner[:m], touching[:m], ends[:, :m]


@njit(cache=True, nogil=True)
def _first_at_least(v: np.ndarray, x: float) -> int:
    """``np.searchsorted(v, x, side="left")``."""
    lo, hi = 0, v.shape[0]
    while lo < hi:
        mid = (lo + hi) // 2
        if v[mid] < x:
            lo = mid + 1
        else:
            hi = mid
    return lo


@njit(cache=True, nogil=True)
def _first_above(v: np.ndarray, x: float) -> int:
    """``np.searchsorted(v, x, side="right")``."""
    lo, hi = 0, v.shape[0]
    while lo < hi:
        mid = (lo + hi) // 2
        if v[mid] <= x:
            lo = mid + 1
        else:
            hi = mid
    return lo


@njit(cache=True, nogil=True)
def nearest_hits(
    a: np.ndarray,
    e: np.ndarray,
    idx: np.ndarray,
    owner: np.ndarray,
    touching: np.ndarray,
    bearing0: np.ndarray,
    bearing1: np.ndarray,
    poses: np.ndarray,
    base: float,
    rel_sorted: np.ndarray,
    order: np.ndarray,
    cw: np.ndarray,
    sw: np.ndarray,
    max_range: float,
    ang_eps: float,
    u_eps: float,
    ranges: np.ndarray,
    tol: float,
    best: np.ndarray,
    on_map: np.ndarray,
) -> None:
    """For every near segment ``s`` (segment ``idx[s]`` of pose ``owner[s]``; ``bearing0``
    / ``bearing1`` the ``arctan2`` bearings of its ends from the sensor) the beams of its
    bearing interval (positions in ``order``, beams sorted by ``rel_sorted``, their angles
    relative to ``base``) and, per beam, the exact intersection (direction ``(cw, sw)[pose,
    beam]``): a hit within ``max_range`` lowers ``best[pose, beam]``. With ``tol >= 0`` (one
    pose), a hit within ``tol`` of ``ranges[beam]`` sets ``on_map[beam]``."""
    n = rel_sorted.shape[0]
    for s in range(idx.shape[0]):
        j = idx[s]
        k = owner[s]
        px = poses[k, 0]
        py = poses[k, 1]
        off = poses[k, 2] + base
        b0 = bearing0[s] - off
        b1 = bearing1[s] - off
        delta = (b1 - b0 + math.pi) % _TWO_PI - math.pi
        lo = b0 if delta >= 0.0 else b1
        span = abs(delta)
        lo = lo % _TWO_PI
        if span >= math.pi - 1e-9 or touching[s]:
            lo = 0.0
            hi = _TWO_PI
        else:
            hi = lo + span
        i0 = _first_at_least(rel_sorted, lo - ang_eps)
        i1 = _first_above(rel_sorted, min(hi, _TWO_PI) + ang_eps)
        j1 = _first_above(rel_sorted, hi - _TWO_PI + ang_eps) if hi > _TWO_PI else 0
        sx = e[j, 0]
        sy = e[j, 1]
        wx = a[j, 0] - px
        wy = a[j, 1] - py
        for part in range(2):
            if part == 0:
                first, last = i0, min(i1, n)
            else:
                first, last = 0, j1
            for pos in range(first, last):
                b = order[pos]
                dx = cw[k, b]
                dy = sw[k, b]
                den = dx * sy - dy * sx
                if den == 0.0:
                    continue
                t = (wx * sy - wy * sx) / den
                u = (wx * dy - wy * dx) / den
                if t >= 0.0 and t <= max_range and u >= -u_eps and u <= 1.0 + u_eps:
                    if t < best[k, b]:
                        best[k, b] = t
                    if tol >= 0.0 and abs(t - ranges[b]) <= tol:
                        on_map[b] = True


def warm_up() -> None:
    """Compile (or load) this module's kernels on tiny inputs."""
    seg = np.array([[1.0, -1.0]])
    e = np.array([[0.0, 2.0]])
    poses = np.zeros((1, 3))
    idx, owner, touching, _ = near_segments(seg, e, np.array([4.0]), poses, 5.0)
    ang = np.zeros(1)
    best = np.full((1, 1), np.inf)
    nearest_hits(
        seg,
        e,
        idx,
        owner,
        touching,
        ang,
        ang,
        poses,
        0.0,
        ang,
        np.zeros(1, dtype=np.intp),
        np.ones((1, 1)),
        np.zeros((1, 1)),
        5.0,
        1e-9,
        1e-12,
        np.zeros(1),
        -1.0,
        best,
        np.zeros(1, dtype=np.bool_),
    )
