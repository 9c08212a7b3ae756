"""Compiled kernels of the feature extraction (implementation details, numba; the
conventions of :mod:`service.core.kernels`).

- :func:`split_cuts`: the cut of a DCE'd polyline into pieces, for
  :func:`service.core.shapes.configuration.split_pieces`;
- :func:`simplify_groups` runs the first-stage DCE (:func:`service.core.kernels.dce.dce_kept`)
  and the cut into pieces (:func:`split_cuts`) of every group of a reading in one call, the
  kernels unchanged, so that a scan or map view pays one call instead of two per group. Its
  caller, :func:`service.core.shapes.configuration._features_from_ranges`, keeps the per-group loop
  as the reference (and for numpy without numba);
- :func:`nearest_segment`: the map segment each point of a map view hit, for
  :func:`service.core.shapes.configuration._hit_segments`;
- :func:`group_spans`: the grouping of a scan (§4.1) with its size filters, as index spans,
  for :func:`service.core.shapes.polylines.group_spans` (whose reference is
  :func:`service.core.shapes.polylines.group_polylines`).
"""

from __future__ import annotations

import numpy as np

from service.core.kernels import njit
from service.core.kernels.dce import dce_kept


@njit(cache=True, nogil=True)
def split_cuts(
    keep: np.ndarray, points: np.ndarray, piece_length: float
) -> tuple[bool, np.ndarray, np.ndarray]:
    """Kernel of :func:`service.core.shapes.configuration.split_pieces` (same arithmetic). Returns
    ``(single, v, bounds)``: ``single`` means "one piece, ``keep`` itself"; otherwise piece
    ``p`` is ``v[bounds[p] : bounds[p + 1] + 1]``."""
    n = points.shape[0]
    cum_raw = np.zeros(n)
    acc = 0.0
    for i in range(n - 1):
        acc += np.hypot(points[i + 1, 0] - points[i, 0], points[i + 1, 1] - points[i, 1])
        cum_raw[i + 1] = acc
    verts = np.empty(n, dtype=np.intp)
    nv = 0
    verts[nv] = keep[0]
    nv += 1
    for t in range(keep.shape[0] - 1):
        a = keep[t]
        b = keep[t + 1]
        span = cum_raw[b] - cum_raw[a]
        nsub = int(span // piece_length)
        if nsub >= 2 and b - a > nsub:
            last = -1
            for q in range(1, nsub):
                target = cum_raw[a] + span * q / nsub
                # searchsorted(cum_raw[a : b + 1], target, side="left") + a
                lo = a
                hi = b + 1
                while lo < hi:
                    mid = (lo + hi) // 2
                    if cum_raw[mid] < target:
                        lo = mid + 1
                    else:
                        hi = mid
                e = lo
                if e < a + 1:
                    e = a + 1
                if e > b - 1:
                    e = b - 1
                if e != last:  # targets increase, so equal values are adjacent
                    verts[nv] = e
                    nv += 1
                    last = e
        verts[nv] = b
        nv += 1
    v = verts[:nv].copy()
    if nv <= 2 and cum_raw[n - 1] < 2.0 * piece_length:
        return True, v, np.zeros(0, dtype=np.intp)
    total = cum_raw[v[nv - 1]]
    bounds = np.empty(nv + 1, dtype=np.intp)
    nb = 0
    bounds[nb] = 0
    nb += 1
    start = 0
    for k in range(1, nv - 1):
        if (
            cum_raw[v[k]] - cum_raw[v[start]] >= piece_length
            and total - cum_raw[v[k]] >= 0.5 * piece_length
        ):
            bounds[nb] = k
            nb += 1
            start = k
    bounds[nb] = nv - 1
    nb += 1
    return False, v, bounds[:nb].copy()


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


@njit(cache=True, nogil=True)
def nearest_segment(points: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """Kernel of :func:`service.core.shapes.configuration._hit_segments`: index of the segment
    nearest to each point (first one on ties), same arithmetic as the numpy version."""
    n = points.shape[0]
    S = segments.shape[0]
    ee = np.empty(S)
    for s in range(S):
        ex = segments[s, 2] - segments[s, 0]
        ey = segments[s, 3] - segments[s, 1]
        v = ex * ex + ey * ey
        ee[s] = v if v > 1e-18 else 1e-18
    out = np.zeros(n, dtype=np.intp)
    for i in range(n):
        px = points[i, 0]
        py = points[i, 1]
        best = np.inf
        bj = 0
        for s in range(S):
            ax = segments[s, 0]
            ay = segments[s, 1]
            ex = segments[s, 2] - ax
            ey = segments[s, 3] - ay
            dx = px - ax
            dy = py - ay
            u = (dx * ex + dy * ey) / ee[s]
            if u < 0.0:
                u = 0.0
            elif u > 1.0:
                u = 1.0
            rx = dx - u * ex
            ry = dy - u * ey
            d2 = rx * rx + ry * ry
            if d2 < best:
                best = d2
                bj = s
        out[i] = bj
    return out


@njit(cache=True, nogil=True)
def group_spans(
    r: np.ndarray,
    a: np.ndarray,
    pts: np.ndarray,
    min_object_distance: float,
    range_factor: float,
    min_points: int,
    min_length: float,
) -> np.ndarray:
    """Kernel of :func:`service.core.polylines.group_spans`: ``(k, 2)`` first and last beam
    (inclusive) of each group of at least ``min_points`` points and ``min_length`` metres, in
    beam order. Beams ``i`` and ``i + 1`` join as in
    :func:`service.core.polylines.group_polylines` (same expressions; the length is summed
    edge by edge, where the reference's numpy sum adds pairwise: they differ in the last bits)."""
    n = r.shape[0]
    out = np.empty((n, 2), dtype=np.intp)
    k = 0
    i = 0
    while i < n:
        if np.isnan(r[i]):
            i += 1
            continue
        s = i
        length = 0.0
        while i + 1 < n and not np.isnan(r[i + 1]):
            dth = abs((a[i + 1] - a[i] + np.pi) % (2.0 * np.pi) - np.pi)
            thr = max(min_object_distance, range_factor * min(r[i], r[i + 1]) * dth)
            d = np.hypot(pts[i + 1, 0] - pts[i, 0], pts[i + 1, 1] - pts[i, 1])
            if not d < thr:
                break
            length += d
            i += 1
        if i - s + 1 >= min_points and length >= min_length:
            out[k, 0] = s
            out[k, 1] = i
            k += 1
        i += 1
    return out[:k].copy()


def warm_up() -> None:
    """Compile (or load) this module's kernels on tiny inputs."""
    p = np.array([[0.0, 0.0], [1.0, 0.1], [2.0, 0.0], [2.0, 1.0]])
    segs = np.array([[0.0, -0.1, 2.0, -0.1], [2.1, -0.1, 2.1, 1.0]])
    split_cuts(np.array([0, 3], dtype=np.intp), p, 1.5)
    simplify_groups(p, np.array([0, 4], dtype=np.intp), 0.04, 1.5)
    nearest_segment(p, segs)
    r = np.hypot(p[:, 0], p[:, 1])
    group_spans(r, np.arctan2(p[:, 1], p[:, 0]), p, 0.1, 4.0, 2, 0.0)
