"""Compiled batch kernels of the shape matching (implementation details, numba).

The per-pair kernels of S* (:func:`service.core.kernels.similarity.arc_tables` and
:func:`service.core.kernels.similarity.shape_dp`) run here over many polyline pairs in one
call, so that a matcher pays one call instead of a Python loop per pair. Each kernel is called
by exactly one public function that owns the concept, its docstring and the numpy / Python
reference (:func:`service.core.shapes.similarity.shape_distances`); the arithmetic is that of the
per-pair kernels, which are called unchanged, so results are identical to them. Beside it, the
mean points of step 1's joined units (:func:`piece_means`). Without numba
(``kernels.HAVE_NUMBA`` is ``False``) the callers run their references.
"""

from __future__ import annotations

import numpy as np

from service.core.kernels import njit
from service.core.kernels.matching import order_dp
from service.core.kernels.similarity import arc_tables, shape_dp


@njit(cache=True, nogil=True)
def _joined(verts: np.ndarray, off: np.ndarray, pieces: np.ndarray, r: int) -> np.ndarray:
    """The polyline of row ``r`` of ``pieces``: the vertex rows of its pieces (indices into
    ``off``, ``-1`` = none) one after the other, as ``np.vstack`` would join them."""
    n = 0
    for t in range(pieces.shape[1]):
        f = pieces[r, t]
        if f >= 0:
            n += off[f + 1] - off[f]
    out = np.empty((n, 2))
    k = 0
    for t in range(pieces.shape[1]):
        f = pieces[r, t]
        if f >= 0:
            for i in range(off[f], off[f + 1]):
                out[k, 0] = verts[i, 0]
                out[k, 1] = verts[i, 1]
                k += 1
    return out


@njit(cache=True, nogil=True)
def shape_distances(
    p_verts: np.ndarray,
    p_off: np.ndarray,
    p_pieces: np.ndarray,
    q_verts: np.ndarray,
    q_off: np.ndarray,
    q_pieces: np.ndarray,
    max_merge: int,
    end_weight: float,
    skip_weight: float,
    upper_bound: float,
) -> tuple[int, int, np.ndarray]:
    """Kernel of :func:`service.core.shapes.similarity.shape_distances`: S* of pair ``r`` =
    (joined ``p_pieces[r]``, joined ``q_pieces[r]``). Returns ``(status, row, out)``: status 0
    ok, else the first failing row's status (1 non-finite, 2 zero length, 3 fewer than two
    vertices; as :class:`~service.core.shapes.similarity.ShapeArcs` checks them, p before q)."""
    R = p_pieces.shape[0]
    out = np.empty(R)
    for r in range(R):
        p = _joined(p_verts, p_off, p_pieces, r)
        if p.shape[0] < 2:
            return 3, r, out
        st, _, _, cum_p, tab_p = arc_tables(p, max_merge)
        if st != 0:
            return st, r, out
        q = _joined(q_verts, q_off, q_pieces, r)
        if q.shape[0] < 2:
            return 3, r, out
        st, _, _, cum_q, tab_q = arc_tables(q, max_merge)
        if st != 0:
            return st, r, out
        best, s, _, _ = shape_dp(
            cum_p, tab_p, cum_q, tab_q, max_merge, max_merge, end_weight, skip_weight, upper_bound
        )
        out[r] = best if s >= 0 else np.inf
    return 0, -1, out


@njit(cache=True, nogil=True)
def piece_means(pts: np.ndarray, off: np.ndarray, pieces: np.ndarray) -> np.ndarray:
    """Kernel of :func:`service.core.shapes.matching._piece_means`: per row of ``pieces`` the mean
    of the point rows of its pieces joined, summed row after row from the first (as numpy's
    ``mean(axis=0)`` of a C-ordered ``(k, 2)`` array sums them) and divided by the count,
    ``(R, 2)``."""
    R = pieces.shape[0]
    out = np.empty((R, 2))
    for r in range(R):
        sx = 0.0
        sy = 0.0
        cnt = 0
        for t in range(pieces.shape[1]):
            f = pieces[r, t]
            if f < 0:
                continue
            for i in range(off[f], off[f + 1]):
                if cnt == 0:
                    sx = pts[i, 0]
                    sy = pts[i, 1]
                else:
                    sx += pts[i, 0]
                    sy += pts[i, 1]
                cnt += 1
        out[r, 0] = sx / cnt
        out[r, 1] = sy / cnt
    return out


@njit(cache=True, nogil=True)
def interval_gates(
    piv: np.ndarray, qiv: np.ndarray, tol: float, lo: float, hi: float
) -> tuple[np.ndarray, np.ndarray]:
    """Kernel of match_with_cost's angular tests (:func:`service.core.shapes.matching._overlaps`
    and :func:`service.core.shapes.matching._single_overlaps`, same arithmetic): ``(single (n, m),
    inside (m,))`` -- scan interval ``i`` and view interval ``j`` (``(start, span)`` rows,
    rad) overlap within ``tol`` (view intervals also at +-2 pi), and the length of each view
    interval inside ``[lo, hi]``."""
    two_pi = 2.0 * np.pi
    n = piv.shape[0]
    m = qiv.shape[0]
    inside = np.zeros(m)
    full = hi - lo >= two_pi - 1e-9
    for j in range(m):
        start = qiv[j, 0]
        span = qiv[j, 1]
        if full:
            inside[j] = span if span <= two_pi else two_pi
            continue
        total = 0.0
        for k in range(3):
            a = start + (k - 1) * two_pi
            e = a + span
            top = e if e <= hi else hi
            bot = a if a >= lo else lo
            d = top - bot
            total = total + (d if d > 0.0 else 0.0)
        inside[j] = total
    single = np.zeros((n, m), dtype=np.bool_)
    for i in range(n):
        ps = piv[i, 0] - tol
        pe = piv[i, 0] + piv[i, 1] + tol
        for j in range(m):
            for k in range(3):
                qs = qiv[j, 0] + (k - 1) * two_pi
                qe = qs + qiv[j, 1]
                if ps < qe and qs < pe:
                    single[i, j] = True
    return single, inside


@njit(cache=True, nogil=True)
def block_pieces(
    cs: np.ndarray, order: np.ndarray, K: int, M: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Kernel of match_with_cost's block identities: per block row ``(i_s, i_e, j_s, j_e)``
    of ``cs`` its scan features ``i_s..i_e`` and its view features ``order[j_s..j_e]`` (``-1``
    padded to ``K``), and its S* key ``((i_s K + i_e - i_s) M^K + sum_b (q_b + 1) M^b)``
    (int64; ``q_b`` the b-th view feature, 0 past the block's end)."""
    R = cs.shape[0]
    m = order.shape[0]
    pp = np.full((R, K), -1, dtype=np.intp)
    qp = np.full((R, K), -1, dtype=np.intp)
    keys = np.empty(R, dtype=np.int64)
    mk = np.int64(1)
    for _ in range(K):
        mk *= M
    for r in range(R):
        i_s = cs[r, 0]
        i_e = cs[r, 1]
        j_s = cs[r, 2]
        j_e = cs[r, 3]
        qk = np.int64(0)
        mb = np.int64(1)
        for b in range(K):
            if b <= i_e - i_s:
                pp[r, b] = i_s + b
            if b <= j_e - j_s:
                f = order[min(j_s + b, m - 1)]
                qp[r, b] = f
                qk += (f + 1) * mb
            mb *= M
        keys[r] = (np.int64(i_s) * K + (i_e - i_s)) * mk + qk
    return pp, qp, keys


@njit(cache=True, nogil=True)
def order_dp_blocks(
    skip_p: np.ndarray,
    skip_q: np.ndarray,
    i_s: np.ndarray,
    i_e: np.ndarray,
    j_s: np.ndarray,
    j_e: np.ndarray,
    cost: np.ndarray,
) -> tuple[float, np.ndarray]:
    """:func:`service.core.kernels.matching.order_dp` for blocks in any order: they are
    grouped by the cell they end at, keeping their order within a cell (a stable counting sort,
    as :func:`service.core.shapes.order_dp.order_preserving_dp` sorts them), then the same DP."""
    n = skip_p.shape[0]
    m = skip_q.shape[0]
    B = i_s.shape[0]
    cell_start = np.zeros(n * m + 1, dtype=np.intp)
    for t in range(B):
        cell_start[i_e[t] * m + j_e[t] + 1] += 1
    for c in range(n * m):
        cell_start[c + 1] += cell_start[c]
    fill = cell_start[:-1].copy()
    bi = np.empty(B, dtype=np.intp)
    bj = np.empty(B, dtype=np.intp)
    bc = np.empty(B)
    for t in range(B):
        c = i_e[t] * m + j_e[t]
        k = fill[c]
        bi[k] = i_s[t]
        bj[k] = j_s[t]
        bc[k] = cost[t]
        fill[c] = k + 1
    return order_dp(skip_p, skip_q, cell_start, bi, bj, bc)
