"""Compiled inner loops of global search's scoring on the distance field (implementation
details, numba; see :mod:`service.core.kernels` for the conventions: the arithmetic follows
the numpy reference expression by expression, no ``fastmath``).

The polish (:meth:`service.core.sensor.scoring.SensorModel.polish`) scores 125 poses per stage and
hypothesis, each over ~80 scan points: ``exp(-d² / 2 s²)`` of the distance-field value ``d``
under every point. The value depends on the field cell alone, so :func:`score_table` computes
it once per cell and sigma (the same expression, so the same bits) and :func:`table_scores`
only looks it up: the exponentials leave the inner loop. The polish itself runs
:func:`grid_scores`, which also computes each point's field row and column once per heading
and offset of its grid.
"""

from __future__ import annotations

import math

import numpy as np

from service.core.kernels import njit


@njit(cache=True, nogil=True)
def _score(d: float, sigma: float, cap: float) -> float:
    d = min(d, cap)
    return math.exp(-0.5 * (d / sigma) ** 2)


@njit(cache=True, nogil=True)
def _cell(
    c: float,
    s: float,
    pose: np.ndarray,
    px: float,
    py: float,
    ox: float,
    oy: float,
    res: float,
    h: int,
    w: int,
) -> tuple[int, int]:
    """Field cell ``(row, column)`` of robot-frame point ``(px, py)`` seen from ``pose``
    (heading cosine ``c``, sine ``s``); ``(-1, -1)`` outside the ``h x w`` field."""
    x = c * px - s * py + pose[0]
    y = s * px + c * py + pose[1]
    ci = math.floor((x - ox) / res)
    cj = math.floor((y - oy) / res)
    if ci >= 0 and ci < w and cj >= 0 and cj < h:
        return int(cj), int(ci)
    return -1, -1


@njit(cache=True, nogil=True)
def outside_score(sigma: float, cap: float) -> float:
    """The field score of a point outside the field (distance capped at ``cap``)."""
    return _score(math.inf, sigma, cap)


@njit(cache=True, nogil=True)
def field_scores(
    dist: np.ndarray,
    ox: float,
    oy: float,
    res: float,
    poses: np.ndarray,
    pts: np.ndarray,
    sigma: float,
    cap: float,
) -> np.ndarray:
    """Kernel of :meth:`service.core.sensor.scoring.SensorModel.field_score` (same arithmetic):
    for each
    pose ``(m, 3)`` the mean over robot-frame ``pts`` ``(k, 2)`` of
    ``exp(-0.5 * (min(d, cap) / sigma) ** 2)``, ``d`` the distance-field value at the point's
    cell (``inf`` outside the field). The reference for :func:`table_scores`."""
    m = poses.shape[0]
    k = pts.shape[0]
    h = dist.shape[0]
    w = dist.shape[1]
    out = np.empty(m)
    for i in range(m):
        c = math.cos(poses[i, 2])
        s = math.sin(poses[i, 2])
        acc = 0.0
        for j in range(k):
            r, q = _cell(c, s, poses[i], pts[j, 0], pts[j, 1], ox, oy, res, h, w)
            d = math.inf
            if r >= 0:
                d = dist[r, q]
            acc += _score(d, sigma, cap)
        out[i] = acc / k
    return out


@njit(cache=True, nogil=True)
def score_table(dist: np.ndarray, sigma: float, cap: float) -> np.ndarray:
    """Per field cell the score :func:`field_scores` adds for a point in it ``(h, w)``."""
    h = dist.shape[0]
    w = dist.shape[1]
    out = np.empty((h, w))
    for r in range(h):
        for c in range(w):
            out[r, c] = _score(float(dist[r, c]), sigma, cap)
    return out


@njit(cache=True, nogil=True)
def table_scores(
    table: np.ndarray,
    outside: float,
    ox: float,
    oy: float,
    res: float,
    poses: np.ndarray,
    pts: np.ndarray,
) -> np.ndarray:
    """:func:`field_scores` with the per-cell scores looked up in ``table``
    (:func:`score_table`) and ``outside`` for points beyond the field: the same sums in the
    same order, so the same results to the bit."""
    m = poses.shape[0]
    k = pts.shape[0]
    h = table.shape[0]
    w = table.shape[1]
    out = np.empty(m)
    for i in range(m):
        c = math.cos(poses[i, 2])
        s = math.sin(poses[i, 2])
        acc = 0.0
        for j in range(k):
            r, q = _cell(c, s, poses[i], pts[j, 0], pts[j, 1], ox, oy, res, h, w)
            if r >= 0:
                acc += table[r, q]
            else:
                acc += outside
        out[i] = acc / k
    return out


@njit(cache=True, nogil=True)
def grid_scores(
    table: np.ndarray,
    outside: float,
    ox: float,
    oy: float,
    res: float,
    base: np.ndarray,
    xs: np.ndarray,
    ys: np.ndarray,
    ths: np.ndarray,
    pts: np.ndarray,
) -> np.ndarray:
    """:func:`table_scores` of the grid of poses ``base[i] + (xs[a], ys[b], ths[c])``, as
    ``(m, len(xs) * len(ys) * len(ths))`` in the order of a ``meshgrid(xs, ys, ths,
    indexing="ij")`` (``c`` fastest): the same poses, sums and bits. A point's field column
    depends only on the heading and ``x``, its row only on the heading and ``y``, so each is
    computed once per heading and offset instead of once per pose."""
    m = base.shape[0]
    k = pts.shape[0]
    h = table.shape[0]
    w = table.shape[1]
    na = xs.shape[0]
    nb = ys.shape[0]
    nc = ths.shape[0]
    out = np.empty((m, na * nb * nc))
    rx = np.empty(k)
    ry = np.empty(k)
    col = np.empty((na, k), dtype=np.int64)
    row = np.empty((nb, k), dtype=np.int64)
    for i in range(m):
        for c in range(nc):
            th = base[i, 2] + ths[c]
            cs = math.cos(th)
            sn = math.sin(th)
            for j in range(k):
                rx[j] = cs * pts[j, 0] - sn * pts[j, 1]
                ry[j] = sn * pts[j, 0] + cs * pts[j, 1]
            for a in range(na):
                x0 = base[i, 0] + xs[a]
                for j in range(k):
                    ci = math.floor((rx[j] + x0 - ox) / res)
                    col[a, j] = int(ci) if ci >= 0 and ci < w else -1
            for b in range(nb):
                y0 = base[i, 1] + ys[b]
                for j in range(k):
                    cj = math.floor((ry[j] + y0 - oy) / res)
                    row[b, j] = int(cj) if cj >= 0 and cj < h else -1
            for a in range(na):
                for b in range(nb):
                    acc = 0.0
                    for j in range(k):
                        q = col[a, j]
                        r = row[b, j]
                        if q >= 0 and r >= 0:
                            acc += table[r, q]
                        else:
                            acc += outside
                    out[i, (a * nb + b) * nc + c] = acc / k
    return out


@njit(cache=True, nogil=True)
def support_counts(
    dist: np.ndarray,
    ox: float,
    oy: float,
    res: float,
    cos_t: np.ndarray,
    sin_t: np.ndarray,
    poses: np.ndarray,
    pts: np.ndarray,
    tol: float,
) -> np.ndarray:
    """Kernel of :meth:`service.core.sensor.scoring.SensorModel.support`: per pose the number of
    robot-frame ``pts`` whose field value is at most ``tol`` (``cos_t`` / ``sin_t`` the poses'
    headings' cosines and sines as numpy computed them, so the points are the reference's)."""
    m = poses.shape[0]
    k = pts.shape[0]
    h = dist.shape[0]
    w = dist.shape[1]
    out = np.zeros(m, dtype=np.int64)
    for i in range(m):
        c = cos_t[i]
        s = sin_t[i]
        n = 0
        for j in range(k):
            r, q = _cell(c, s, poses[i], pts[j, 0], pts[j, 1], ox, oy, res, h, w)
            if r >= 0 and dist[r, q] <= tol:
                n += 1
        out[i] = n
    return out


@njit(cache=True, nogil=True)
def field_crossings(
    dist: np.ndarray,
    ox: float,
    oy: float,
    res: float,
    px: np.ndarray,
    py: np.ndarray,
    cos_b: np.ndarray,
    sin_b: np.ndarray,
    lim: np.ndarray,
    max_steps: int,
) -> np.ndarray:
    """Kernel of :meth:`service.core.sensor.scoring.SensorModel.crossings` (the same steps): per
    pose ``i`` (sensor at ``px[i], py[i]``) the number of beams ``j`` (direction
    ``cos_b[i, j], sin_b[i, j]``) that meet a drawn wall before ``lim[j]`` metres, marching
    along the beam by each cell's clearance (sphere tracing on the distance field)."""
    m = cos_b.shape[0]
    k = cos_b.shape[1]
    h = dist.shape[0]
    w = dist.shape[1]
    wall = res
    least = 0.5 * res
    out = np.zeros(m, dtype=np.int64)
    for i in range(m):
        n = 0
        for j in range(k):
            t = 0.0
            steps = 0
            while t < lim[j] and steps < max_steps:
                ci = math.floor((px[i] + t * cos_b[i, j] - ox) / res)
                cj = math.floor((py[i] + t * sin_b[i, j] - oy) / res)
                if ci < 0 or ci >= w or cj < 0 or cj >= h:
                    break
                d = float(dist[int(cj), int(ci)])
                if d <= wall:
                    n += 1
                    break
                t += max(d - 1.5 * res, least)
                steps += 1
        out[i] = n
    return out


def warm_up(p: np.ndarray) -> None:
    """Compile (or load) every kernel of this module on tiny inputs."""
    field = np.ones((2, 2), dtype=np.float32)
    z = np.zeros((1, 3))
    field_scores(field, 0.0, 0.0, 0.5, z, p, 0.1, 10.0)
    table = score_table(field, 0.1, 10.0)
    table_scores(table, 0.0, 0.0, 0.0, 0.5, z, p)
    g = np.zeros(1)
    grid_scores(table, 0.0, 0.0, 0.0, 0.5, z, g, g, g, p)
    support_counts(field, 0.0, 0.0, 0.5, np.ones(1), np.zeros(1), z, p, 0.1)
    one = np.ones((1, 1))
    field_crossings(field, 0.0, 0.0, 0.5, g, g, one, one, np.ones(1), 4)
    near_mask(np.zeros((1, 4)), p, 0.1)
    outside_score(0.1, 10.0)


@njit(cache=True, nogil=True)
def near_mask(segments: np.ndarray, points: np.ndarray, radius: float) -> np.ndarray:
    """:func:`service.core.sensor.mapmodel.near_mask` (its numpy reference) in loops: per
    segment, whether any point lies within ``radius`` (the same squared distance, compared
    with ``radius * radius``; a segment stops at its first such point)."""
    n_seg = segments.shape[0]
    r2 = radius * radius
    out = np.zeros(n_seg, dtype=np.bool_)
    for j in range(n_seg):
        ax = segments[j, 0]
        ay = segments[j, 1]
        ex = segments[j, 2] - ax
        ey = segments[j, 3] - ay
        ee = max(ex * ex + ey * ey, 1e-18)
        for i in range(points.shape[0]):
            dx = points[i, 0] - ax
            dy = points[i, 1] - ay
            u = min(max((dx * ex + dy * ey) / ee, 0.0), 1.0)
            fx = dx - u * ex
            fy = dy - u * ey
            if fx * fx + fy * fy <= r2:
                out[j] = True
                break
    return out
