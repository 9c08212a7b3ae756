"""Compiled batch kernels of the shape matching (implementation details, numba).

The per-pair kernels of S* (:func:`service.core._kernels.arc_tables` and
:func:`service.core._kernels.shape_dp`) run here over many polyline pairs in one call, so that a
matcher pays one call instead of a Python loop per pair. Each kernel is called by exactly one
public function that owns the concept, its docstring and the numpy / Python reference
(:func:`service.core.similarity.shape_distances`); the arithmetic is that of the per-pair
kernels, which are called unchanged, so results are identical to them. Without numba
(``_kernels.HAVE_NUMBA`` is ``False``) the callers run their references.
"""

from __future__ import annotations

import numpy as np

from service.core._kernels import arc_tables, njit, shape_dp


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
    """Kernel of :func:`service.core.similarity.shape_distances`: S* of pair ``r`` =
    (joined ``p_pieces[r]``, joined ``q_pieces[r]``). Returns ``(status, row, out)``: status 0
    ok, else the first failing row's status (1 non-finite, 2 zero length, 3 fewer than two
    vertices; as :class:`~service.core.similarity.ShapeArcs` checks them, p before q)."""
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
