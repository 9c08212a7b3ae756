"""Compiled inner loops of the configuration matching of eq. 5 (implementation details,
numba; the conventions of :mod:`service.core.kernels`: the arithmetic follows the numpy /
Python references expression by expression, no ``fastmath``).

- :func:`angular_intervals`: each map polyline's bearing interval seen from the estimate, for
  :func:`service.core.shapes.matching.map_order`;
- :func:`block_candidates` and :func:`range_means`: the candidate blocks and the centroids of
  their scan points, for :func:`service.core.shapes.matching.match_with_cost`;
- :func:`order_dp`: the extended DP of §5.2, for
  :func:`service.core.shapes.order_dp.order_preserving_dp` (called by
  :func:`service.core.kernels.shape.order_dp_blocks`, which groups the blocks by end cell).
"""

from __future__ import annotations

import math

import numpy as np

from service.core.kernels import TWO_PI, njit, wrap


@njit(cache=True, nogil=True)
def angular_intervals(points: np.ndarray, offsets: np.ndarray, viewpoint: np.ndarray) -> np.ndarray:
    """Kernel of :func:`service.core.shapes.matching.map_order`: per polyline ``f`` (rows
    ``offsets[f] .. offsets[f + 1] - 1`` of ``points``) the ``(start, span)`` of its bearings
    seen from ``viewpoint`` ``[x, y, theta]``, exactly as ``matching.angular_interval``."""
    F = offsets.shape[0] - 1
    out = np.empty((F, 2))
    vx = viewpoint[0]
    vy = viewpoint[1]
    th = viewpoint[2]
    for f in range(F):
        a = offsets[f]
        e = offsets[f + 1]
        b0 = math.atan2(points[a, 1] - vy, points[a, 0] - vx) - th
        prev = b0
        cum = 0.0
        lo = 0.0
        hi = 0.0
        for i in range(a + 1, e):
            b = math.atan2(points[i, 1] - vy, points[i, 0] - vx) - th
            cum += ((b - prev) + math.pi) % TWO_PI - math.pi
            if cum < lo:
                lo = cum
            if cum > hi:
                hi = cum
            prev = b
        out[f, 0] = wrap(b0 + lo)
        out[f, 1] = hi - lo
    return out


@njit(cache=True, nogil=True)
def block_candidates(single: np.ndarray, K: int, join_total: bool) -> np.ndarray:
    """Kernel of the candidate blocks of :func:`service.core.shapes.matching.match_with_cost`:
    rows ``(i_s, i_e, j_s, j_e)`` with ``single[i_s, j_s]`` and ``single[i_e, j_e]``, runs of
    up to ``K`` polylines (``K`` in total over both sides with ``join_total``), in the order
    (i_s, j_s) row-major, then ``i_e``, then ``j_e``."""
    n, m = single.shape
    cap = 16
    out = np.empty((cap, 4), dtype=np.intp)
    c = 0
    for i_s in range(n):
        for j_s in range(m):
            if not single[i_s, j_s]:
                continue
            for a in range(K):
                i_e = i_s + a
                if i_e >= n:
                    break
                nb = K - a if join_total else K
                for b in range(nb):
                    j_e = j_s + b
                    if j_e >= m:
                        break
                    if single[i_e, j_e]:
                        if c == cap:
                            cap *= 2
                            bigger = np.empty((cap, 4), dtype=np.intp)
                            bigger[:c] = out[:c]
                            out = bigger
                        out[c, 0] = i_s
                        out[c, 1] = i_e
                        out[c, 2] = j_s
                        out[c, 3] = j_e
                        c += 1
    return out[:c].copy()


@njit(cache=True, nogil=True)
def range_means(P: np.ndarray, beg: np.ndarray, end: np.ndarray) -> np.ndarray:
    """Mean of the rows ``P[beg[k] : end[k]]`` per ``k`` (sums in row order, as
    ``np.bincount`` forms them), ``(K, 2)``."""
    K = beg.shape[0]
    out = np.empty((K, 2))
    for k in range(K):
        sx = 0.0
        sy = 0.0
        for i in range(beg[k], end[k]):
            sx += P[i, 0]
            sy += P[i, 1]
        cnt = float(end[k] - beg[k])
        out[k, 0] = sx / cnt
        out[k, 1] = sy / cnt
    return out


@njit(cache=True, nogil=True)
def order_dp(
    skip_p: np.ndarray,
    skip_q: np.ndarray,
    cell_start: np.ndarray,
    b_is: np.ndarray,
    b_js: np.ndarray,
    b_cost: np.ndarray,
) -> tuple[float, np.ndarray]:
    """Kernel of :func:`service.core.shapes.order_dp.order_preserving_dp` (eq. 5), same recurrence
    and tie order. Blocks ending at cell ``(i_e, j_e)`` are ``cell_start[i_e * m + j_e] ..
    cell_start[i_e * m + j_e + 1] - 1`` of ``b_is, b_js, b_cost`` (in their original order).
    Returns ``(cost, path (L, 4) rows (i_s, i_e, j_s, j_e))``."""
    n = skip_p.shape[0]
    m = skip_q.shape[0]
    C = np.empty((n + 1, m + 1))
    bi = np.empty((n + 1, m + 1), dtype=np.intp)
    bj = np.empty((n + 1, m + 1), dtype=np.intp)
    bf = np.zeros((n + 1, m + 1), dtype=np.bool_)
    C[0, 0] = 0.0
    for i in range(1, n + 1):
        C[i, 0] = C[i - 1, 0] + skip_p[i - 1]
        bi[i, 0] = i - 1
        bj[i, 0] = 0
    for j in range(1, m + 1):
        C[0, j] = C[0, j - 1] + skip_q[j - 1]
        bi[0, j] = 0
        bj[0, j] = j - 1
    for i in range(1, n + 1):
        sp = skip_p[i - 1]
        for j in range(1, m + 1):
            best = C[i - 1, j] + sp
            ai = i - 1
            aj = j
            af = False
            c = C[i, j - 1] + skip_q[j - 1]
            if c < best:
                best = c
                ai = i
                aj = j - 1
            cell = (i - 1) * m + (j - 1)
            for t in range(cell_start[cell], cell_start[cell + 1]):
                c = C[b_is[t], b_js[t]] + b_cost[t]
                if c < best:
                    best = c
                    ai = b_is[t]
                    aj = b_js[t]
                    af = True
            C[i, j] = best
            bi[i, j] = ai
            bj[i, j] = aj
            bf[i, j] = af
    out = np.empty((n + m, 4), dtype=np.intp)
    L = 0
    i = n
    j = m
    while i > 0 or j > 0:
        pi = bi[i, j]
        pj = bj[i, j]
        if bf[i, j]:
            out[L, 0] = pi
            out[L, 1] = i - 1
            out[L, 2] = pj
            out[L, 3] = j - 1
            L += 1
        i = pi
        j = pj
    return C[n, m], out[:L][::-1].copy()


def warm_up() -> None:
    """Compile (or load) this module's kernels on tiny inputs."""
    p = np.array([[0.0, 0.0], [1.0, 0.1], [2.0, 0.0], [2.0, 1.0]])
    z = np.zeros(1, dtype=np.intp)
    angular_intervals(p, np.array([0, 4], dtype=np.intp), np.zeros(3))
    block_candidates(np.ones((2, 2), dtype=np.bool_), 3, True)
    range_means(p, z, np.array([4]))
    cell = np.array([0, 0, 1], dtype=np.intp)
    order_dp(np.ones(1), np.ones(1), cell, z, z, np.ones(1))
