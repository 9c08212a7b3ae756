"""Compiled inner loops of S*, the shape distance (implementation details, numba; the
conventions of :mod:`service.core.kernels`: the arithmetic follows the pure-Python reference
expression by expression, no ``fastmath``).

- :func:`arc_tables`: a polyline without its repeated vertices and its chord tables, for
  :class:`service.core.shapes.similarity.ShapeArcs`;
- :func:`shape_dp`: the DP of S* over two such tables, for
  :func:`service.core.shapes.similarity._dp` (its pure-Python reference is
  :func:`service.core.shapes.similarity_reference.dp_python`).

:func:`service.core.kernels.shape.shape_distances` runs both over many polyline pairs in one
call.
"""

from __future__ import annotations

import math

import numpy as np

from service.core.kernels import TWO_PI, njit


@njit(cache=True, nogil=True)
def arc_tables(
    p: np.ndarray, max_merge: int
) -> tuple[int, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Kernel of :class:`service.core.shapes.similarity.ShapeArcs`: drop repeated vertices of ``p``
    ``(k, 2)`` and build the chord tables. Returns ``(status, x, y, cum, tab)`` with status 0
    ok, 1 non-finite coordinate, 2 zero length; ``tab[0 | 1 | 2, a, i]`` = chord length,
    direction and merge cost from vertex ``i`` over ``a`` arcs (valid for ``i < k - a``)."""
    n = p.shape[0]
    x = np.empty(n)
    y = np.empty(n)
    cum = np.empty(n)
    x[0] = p[0, 0]
    y[0] = p[0, 1]
    cum[0] = 0.0
    k = 1
    for i in range(n):
        xi = p[i, 0]
        yi = p[i, 1]
        if not (math.isfinite(xi) and math.isfinite(yi)):
            return 1, x[:0], y[:0], cum[:0], np.zeros((3, 1, 1))
        d = math.hypot(xi - x[k - 1], yi - y[k - 1])
        if d > 1e-12:
            x[k] = xi
            y[k] = yi
            cum[k] = cum[k - 1] + d
            k += 1
    if k < 2:
        return 2, x[:0], y[:0], cum[:0], np.zeros((3, 1, 1))
    tab = np.zeros((3, max_merge + 1, k))
    for a in range(1, max_merge + 1):
        for i in range(k - a):
            dx = x[i + a] - x[i]
            dy = y[i + a] - y[i]
            c = math.hypot(dx, dy)
            tab[0, a, i] = c
            tab[1, a, i] = math.atan2(dy, dx)
            m = cum[i + a] - cum[i] - c
            tab[2, a, i] = m if m > 0.0 else 0.0
    return 0, x[:k].copy(), y[:k].copy(), cum[:k].copy(), tab


@njit(cache=True, nogil=True)
def shape_dp(
    cum_p: np.ndarray,
    tab_p: np.ndarray,
    cum_q: np.ndarray,
    tab_q: np.ndarray,
    mp: int,
    mq: int,
    end_weight: float,
    skip_weight: float,
    upper_bound: float,
) -> tuple[float, int, int, np.ndarray]:
    """Kernel of S* (:func:`service.core.shapes.similarity._dp`, same states, moves, order and
    pruning). Returns ``(best, state, target, back)``; ``state < 0`` when nothing is below
    ``upper_bound``."""
    kp = cum_p.shape[0]
    kq = cum_q.shape[0]
    lastp = kp - 1
    lastq = kq - 1
    tot_p = cum_p[lastp]
    tot_q = cum_q[lastq]
    lbw = min(end_weight, skip_weight, 1.0)
    pi = math.pi
    inf = np.inf
    n = kp * kq
    cost = np.full(n, inf)
    pend = np.zeros(n)
    dpi = np.zeros(n)
    dqi = np.zeros(n)
    lpi = np.zeros(n)
    lqi = np.zeros(n)
    start = np.zeros(n, dtype=np.bool_)
    back = np.full(n, -1, dtype=np.intp)
    for j in range(lastq):
        cost[j] = skip_weight * cum_q[j]
        start[j] = True
    for i in range(1, lastp):
        cost[i * kq] = skip_weight * cum_p[i]
        start[i * kq] = True
    best = upper_bound
    best_s = -1
    best_t = -1
    for i in range(lastp):
        row = i * kq
        amax = lastp - i
        if amax > mp:
            amax = mp
        rem_p = tot_p - cum_p[i]
        for j in range(lastq):
            s = row + j
            c0 = cost[s]
            if c0 == inf:
                continue
            is_start = start[s]
            base = c0 if is_start else c0 + pend[s]
            imb = rem_p - (tot_q - cum_q[j])
            if base + lbw * (imb if imb > 0.0 else -imb) >= best:
                continue
            di = dpi[s]
            dj = dqi[s]
            li = lpi[s]
            lj = lqi[s]
            bmax = lastq - j
            if bmax > mq:
                bmax = mq
            nmoves = amax + bmax - 1
            for mv in range(nmoves):
                # (1, 1), then (a, 1) for a = 2..amax, then (1, b) for b = 2..bmax
                if mv == 0:
                    a = 1
                    b = 1
                elif mv < amax:
                    a = mv + 1
                    b = 1
                else:
                    a = 1
                    b = mv - amax + 2
                i2 = i + a
                j2 = j + b
                lp = tab_p[0, a, i]
                lq = tab_q[0, b, j]
                c = base + tab_p[2, a, i] + tab_q[2, b, j]
                mis = lp - lq if lp > lq else lq - lp
                if is_start:
                    mis_w = end_weight
                else:
                    dt = (tab_p[1, a, i] - di) - (tab_q[1, b, j] - dj)
                    dt = abs((dt + pi) % TWO_PI - pi)
                    w = lp if lp < lq else lq
                    if li < w:
                        w = li
                    if lj < w:
                        w = lj
                    c += dt * w
                    mis_w = 1.0
                if i2 == lastp or j2 == lastq:
                    total = (
                        c
                        + end_weight * mis
                        + skip_weight * ((tot_p - cum_p[i2]) + (tot_q - cum_q[j2]))
                    )
                    if total < best:
                        best = total
                        best_s = s
                        best_t = i2 * kq + j2
                    continue
                pm = mis_w * mis
                if c + pm >= best:
                    continue
                s2 = i2 * kq + j2
                if c + pm < cost[s2] + pend[s2]:
                    cost[s2] = c
                    pend[s2] = pm
                    dpi[s2] = tab_p[1, a, i]
                    dqi[s2] = tab_q[1, b, j]
                    lpi[s2] = lp
                    lqi[s2] = lq
                    start[s2] = False
                    back[s2] = s
    return best, best_s, best_t, back


def warm_up() -> None:
    """Compile (or load) this module's kernels on tiny inputs."""
    p = np.array([[0.0, 0.0], [1.0, 0.1], [2.0, 0.0], [2.0, 1.0]])
    _, _, _, cum, tab = arc_tables(p, 4)
    shape_dp(cum, tab, cum, tab, 4, 4, 0.1, 0.5, np.inf)
