"""Pure-Python reference of S*'s dynamic programme (paper §5.1; the cost terms and the DP's
states are described in :mod:`service.core.shapes.similarity`).

:func:`dp_python` is what :func:`service.core.shapes.similarity._dp` runs when the polylines carry
no numpy tables (numba not installed); the compiled kernel
:func:`service.core.kernels.similarity.shape_dp` follows it expression by expression (same
states, moves, order and pruning), and tests compare the two. Plain Python lists and floats:
polylines have a handful of vertices, where numpy's per-call overhead dominates.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from service.core.shapes.similarity import ShapeArcs

_TWO_PI = 2.0 * math.pi


_MOVES_CACHE: dict[tuple[int, int], tuple[tuple[int, int], ...]] = {}


def _moves(amax: int, bmax: int) -> tuple[tuple[int, int], ...]:
    """Allowed (a, b) steps (1:1, n:1, 1:n) when at most amax / bmax arcs remain usable."""
    key = (amax, bmax)
    m = _MOVES_CACHE.get(key)
    if m is None:
        m = ((1, 1), *((a, 1) for a in range(2, amax + 1)), *((1, b) for b in range(2, bmax + 1)))
        _MOVES_CACHE[key] = m
    return m


def dp_python(
    P: ShapeArcs,
    Q: ShapeArcs,
    max_merge: int,
    end_weight: float,
    skip_weight: float,
    want_path: bool,
    upper_bound: float = math.inf,
) -> tuple[float, list[tuple[int, int, int, int]]]:
    """Pure-Python reference of :func:`service.core.shapes.similarity._dp` (same arguments and
    result)."""
    kp, kq = P.k, Q.k
    lastp, lastq = kp - 1, kq - 1
    cum_p, cum_q = P.cum, Q.cum
    tot_p, tot_q = cum_p[-1], cum_q[-1]
    Lp, Dp, Mp = P.chord_len, P.chord_dir, P.merge_cost
    Lq, Dq, Mq = Q.chord_len, Q.chord_dir, Q.merge_cost
    mp = min(max_merge, P.max_merge)
    mq = min(max_merge, Q.max_merge)
    lbw = min(end_weight, skip_weight, 1.0)
    pi = math.pi
    inf = math.inf
    n = kp * kq
    cost = [inf] * n  # accumulated cost excluding the incoming pair's length misfit
    pend = [0.0] * n  # weighted length misfit of the incoming pair (still pending)
    dpi = [0.0] * n  # incoming chord direction in p
    dqi = [0.0] * n
    lpi = [0.0] * n  # incoming chord length in p
    lqi = [0.0] * n
    start = [False] * n  # state is a start (no incoming chord)
    back = [-1] * n
    # Starts: p's first vertex against any q vertex (q's leading arcs skipped) and vice versa.
    for j in range(lastq):
        cost[j] = skip_weight * cum_q[j]
        start[j] = True
    for i in range(1, lastp):
        cost[i * kq] = skip_weight * cum_p[i]
        start[i * kq] = True
    best = upper_bound
    best_end = (-1, -1)  # (state, target) of the best final transition
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
            if not is_start:
                di, dj, li, lj = dpi[s], dqi[s], lpi[s], lqi[s]
            bmax = lastq - j
            if bmax > mq:
                bmax = mq
            for a, b in _moves(amax, bmax):
                i2 = i + a
                j2 = j + b
                lp = Lp[a][i]
                lq = Lq[b][j]
                c = base + Mp[a][i] + Mq[b][j]
                mis = lp - lq if lp > lq else lq - lp
                if is_start:
                    mis_w = end_weight
                else:
                    dt = (Dp[a][i] - di) - (Dq[b][j] - dj)
                    dt = abs((dt + pi) % _TWO_PI - pi)
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
                        best_end = (s, i2 * kq + j2)
                    continue
                pm = mis_w * mis
                if c + pm >= best:
                    continue
                s2 = i2 * kq + j2
                if c + pm < cost[s2] + pend[s2]:
                    cost[s2] = c
                    pend[s2] = pm
                    dpi[s2] = Dp[a][i]
                    dqi[s2] = Dq[b][j]
                    lpi[s2] = lp
                    lqi[s2] = lq
                    start[s2] = False
                    back[s2] = s
    if best_end[0] < 0:
        return inf, []
    path: list[tuple[int, int, int, int]] = []
    if want_path:
        s, s2 = best_end
        while s >= 0:
            path.append((s // kq, s2 // kq, s % kq, s2 % kq))
            s2 = s
            s = back[s]
        path.reverse()
    return best, path
