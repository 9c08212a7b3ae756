"""Compiled batch kernel of the feature extraction (implementation detail, numba).

:func:`simplify_groups` runs the first-stage DCE (:func:`service.core._kernels.dce_kept`) and
the cut into pieces (:func:`service.core._kernels.split_cuts`) of every group of a reading in
one call, the kernels unchanged, so that a scan or map view pays one call instead of two per
group. Its caller, :func:`service.core.configuration._features_from_ranges`, keeps the
per-group loop as the reference (and for numpy without numba).
"""

from __future__ import annotations

import numpy as np

from service.core._kernels import dce_kept, njit, split_cuts


@njit(cache=True, nogil=True)
def simplify_groups(
    pts: np.ndarray, off: np.ndarray, threshold: float, piece_length: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Group ``g`` is the rows ``off[g] : off[g + 1]`` of ``pts`` ``(N, 2)`` (>= 2 rows).
    Returns ``(verts, voff, pieces)``: group ``g``'s vertex indices (into its own rows) are
    ``verts[voff[g] : voff[g + 1]]`` -- the DCE-kept vertices when the group stays one piece,
    else the cut vertices -- and ``pieces`` rows ``(g, a, b)`` give its pieces
    ``verts[voff[g] + a : voff[g] + b + 1]`` (one row ``(g, 0, len - 1)`` for one piece)."""
    G = off.shape[0] - 1
    n_all = off[G] - off[0]
    verts = np.empty(n_all, dtype=np.intp)
    voff = np.zeros(G + 1, dtype=np.intp)
    pieces = np.empty((n_all, 3), dtype=np.intp)
    nv = 0
    npc = 0
    for g in range(G):
        p = pts[off[g] : off[g + 1]]
        keep = dce_kept(p, threshold)
        use = keep
        bounds = np.zeros(0, dtype=np.intp)
        if piece_length > 0 and p.shape[0] >= 3:
            single, v, b = split_cuts(keep, p, piece_length)
            if not single and b.shape[0] > 2:
                use = v
                bounds = b
        for i in range(use.shape[0]):
            verts[nv + i] = use[i]
        if bounds.shape[0] == 0:
            pieces[npc, 0] = g
            pieces[npc, 1] = 0
            pieces[npc, 2] = use.shape[0] - 1
            npc += 1
        else:
            for k in range(bounds.shape[0] - 1):
                pieces[npc, 0] = g
                pieces[npc, 1] = bounds[k]
                pieces[npc, 2] = bounds[k + 1]
                npc += 1
        nv += use.shape[0]
        voff[g + 1] = nv
    return verts[:nv].copy(), voff, pieces[:npc].copy()
