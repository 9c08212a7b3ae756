"""Iso-contours of a sampled 2D field (marching squares) linked into polylines.

Shared by the occupancy-grid import (:mod:`service.adapters.maps.grid`, contours of the occupied
mask) and the map builder (:mod:`service.adapters.maps.build`, ridges of the hit density).

Index space: a field ``f`` of shape ``(h, w)`` is sampled at integer points ``(row, col)``;
contour vertices are returned as ``(k, 2)`` float64 arrays of ``(row, col)`` with fractional
parts (linear interpolation along the grid edge that the contour crosses). Each returned
polyline is oriented so that the region ``f >= level`` lies on its **left** in the
right-handed plane ``(x, y) = (col, row)`` (cross product of the direction of travel and the
offset to the region is positive); a closed contour repeats its first vertex last. (Drawn as
an image, with rows growing downwards, that region appears on the right.)

Ambiguous squares (two diagonal corners above the level, two below) are resolved by the mean
of the four corners: if it is ``>= level`` the two "above" corners are joined, so a binary
mask contoured at 0.5 is 8-connected on its ``>= level`` side.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from service.core import numeric
from service.errors import LocalizationError

# Corners of a square, in (x = col, y = row) offsets: p0 top-left, p1 top-right,
# p2 bottom-right, p3 bottom-left. Edge k joins corner k and corner (k + 1) % 4:
# e0 top, e1 right, e2 bottom, e3 left.
_CORNERS = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
_EDGE_MID = 0.5 * (_CORNERS + np.roll(_CORNERS, -1, axis=0))


def _segment_table() -> list[list[tuple[int, int]]]:
    """Oriented edge pairs for the 16 corner cases and 2 extra saddle variants.

    Index ``case`` (bit k set: corner k is ``>= level``) for 0..15, where the saddles 5 and 10
    use the "joined above" resolution; indices 16 and 17 are the saddles 5 and 10 with the
    "joined below" resolution. Each entry is a list of ``(from_edge, to_edge)`` with the
    ``>= level`` side on the left of the segment (right-handed x = col, y = row plane).
    """

    def orient(a: int, b: int, above: list[int]) -> tuple[int, int]:
        pa, pb = _EDGE_MID[a], _EDGE_MID[b]
        d = pb - pa
        # any above corner adjacent to the cut decides the side; use their mean
        c = _CORNERS[above].mean(axis=0) - pa
        cross = d[0] * c[1] - d[1] * c[0]
        return (a, b) if cross > 0 else (b, a)

    table: list[list[tuple[int, int]]] = []
    for case in range(18):
        bits = case if case < 16 else (5 if case == 16 else 10)
        above = [k for k in range(4) if bits >> k & 1]
        crossed = [k for k in range(4) if (bits >> k & 1) != (bits >> ((k + 1) % 4) & 1)]
        if not crossed:
            table.append([])
            continue
        if len(crossed) == 2:
            a, b = crossed
            table.append([orient(a, b, above)])
            continue
        # saddle: four crossed edges; isolate either the below corners (joined above, cases
        # 5/10) or the above corners (joined below, cases 16/17).
        joined_above = case < 16
        isolated = [k for k in range(4) if bool(bits >> k & 1) != joined_above]
        segs = []
        for k in isolated:
            a, b = (k - 1) % 4, k  # the two edges adjacent to corner k
            if joined_above:
                # the isolated corner is below: above is everything else, i.e. the side
                # away from corner k
                others = [j for j in range(4) if j != k]
                segs.append(orient(a, b, others))
            else:
                segs.append(orient(a, b, [k]))
        table.append(segs)
    return table


_TABLE = _segment_table()


def marching_squares(
    field: np.ndarray, level: float, mask: np.ndarray | None = None
) -> list[np.ndarray]:
    """Iso-contours ``field == level`` as linked polylines in ``(row, col)`` index space.

    ``field`` ``(h, w)`` float; ``mask`` (optional, same shape, bool) marks samples that may be
    used: a square contributes contour segments only when its four corners are all in the mask
    (non-finite samples are always excluded). Returns a list of ``(k, 2)`` float64 arrays of
    ``(row, col)``, k >= 2, oriented with ``field >= level`` on the left (module docstring);
    closed contours repeat their first vertex last. Open contours end where the field or the
    mask ends. Deterministic: polylines are ordered by their first vertex's position in the
    grid (row-major), open ones first.
    """
    f = np.asarray(field, dtype=np.float64)
    if f.ndim != 2:
        raise LocalizationError(f"marching_squares: expected a 2-D field, got shape {f.shape}")
    h, w = f.shape
    if h < 2 or w < 2:
        return []
    valid = np.isfinite(f)
    if mask is not None:
        m = np.asarray(mask, dtype=bool)
        if m.shape != f.shape:
            raise LocalizationError(f"marching_squares: mask shape {m.shape} != {f.shape}")
        valid &= m
    fz = np.where(valid, f, level - 1.0)
    above = fz >= level
    a0, a1 = above[:-1, :-1], above[:-1, 1:]
    a2, a3 = above[1:, 1:], above[1:, :-1]
    case = (a0.astype(np.int8) | (a1.astype(np.int8) << 1) | (a2.astype(np.int8) << 2)) | (
        a3.astype(np.int8) << 3
    )
    ok = valid[:-1, :-1] & valid[:-1, 1:] & valid[1:, 1:] & valid[1:, :-1]
    case = np.where(ok, case, 0)
    saddle = (case == 5) | (case == 10)
    if np.any(saddle):
        centre = 0.25 * (fz[:-1, :-1] + fz[:-1, 1:] + fz[1:, 1:] + fz[1:, :-1])
        below_centre = saddle & (centre < level)
        case = np.where(below_centre & (case == 5), 16, case)
        case = np.where(below_centre & (case == 10), 17, case)

    n_h = h * (w - 1)  # horizontal edges (r, c)-(r, c+1): id r * (w - 1) + c

    def edge_ids(rr: np.ndarray, cc: np.ndarray, e: int) -> np.ndarray:
        if e == 0:
            return rr * (w - 1) + cc
        if e == 2:
            return (rr + 1) * (w - 1) + cc
        if e == 3:
            return n_h + rr * w + cc
        return n_h + rr * w + cc + 1  # e == 1

    src_l: list[np.ndarray] = []
    dst_l: list[np.ndarray] = []
    for c_idx in range(1, 18):
        segs = _TABLE[c_idx]
        if not segs:
            continue
        rr, cc = np.nonzero(case == c_idx)
        if rr.size == 0:
            continue
        rr = rr.astype(np.int64)
        cc = cc.astype(np.int64)
        for a, b in segs:
            src_l.append(edge_ids(rr, cc, a))
            dst_l.append(edge_ids(rr, cc, b))
    if not src_l:
        return []
    src = np.concatenate(src_l)
    dst = np.concatenate(dst_l)

    # vertex position of every crossed edge
    used = np.unique(np.concatenate([src, dst]))
    is_h = used < n_h
    pos = np.empty((used.size, 2))
    uh = used[is_h]
    r0, c0 = uh // (w - 1), uh % (w - 1)
    fa, fb = fz[r0, c0], fz[r0, c0 + 1]
    t = np.clip((level - fa) / np.where(fb != fa, fb - fa, 1.0), 0.0, 1.0)
    pos[is_h, 0] = r0
    pos[is_h, 1] = c0 + t
    uv = used[~is_h] - n_h
    r0, c0 = uv // w, uv % w
    fa, fb = fz[r0, c0], fz[r0 + 1, c0]
    t = np.clip((level - fa) / np.where(fb != fa, fb - fa, 1.0), 0.0, 1.0)
    pos[~is_h, 0] = r0 + t
    pos[~is_h, 1] = c0

    # link: every crossed edge has at most one outgoing and one incoming segment
    s_loc = np.searchsorted(used, src)
    d_loc = np.searchsorted(used, dst)
    n = used.size
    nxt = np.full(n, -1, dtype=np.int64)
    nxt[s_loc] = d_loc
    has_in = np.zeros(n, dtype=bool)
    has_in[d_loc] = True
    seen = np.zeros(n, dtype=bool)
    nxt_l: list[int] = nxt.tolist()
    seen_l: list[bool] = seen.tolist()
    out_open: list[np.ndarray] = []
    out_closed: list[np.ndarray] = []
    starts_open = np.nonzero(~has_in & (nxt >= 0))[0].tolist()
    for s in starts_open:
        chain = [s]
        seen_l[s] = True
        j = nxt_l[s]
        while j >= 0 and not seen_l[j]:
            seen_l[j] = True
            chain.append(j)
            j = nxt_l[j]
        if len(chain) >= 2:
            out_open.append(pos[chain])
    for s in range(n):
        if seen_l[s] or nxt_l[s] < 0:
            continue
        chain = [s]
        seen_l[s] = True
        j = nxt_l[s]
        while j >= 0 and not seen_l[j]:
            seen_l[j] = True
            chain.append(j)
            j = nxt_l[j]
        if j == s:
            chain.append(s)
        if len(chain) >= 2:
            out_closed.append(pos[chain])
    return out_open + out_closed


def is_closed(p: np.ndarray, tol: float = 1e-9) -> bool:
    """True if the polyline ``(k, 2)`` has k >= 4 and repeats its first vertex last."""
    return p.shape[0] >= 4 and bool(np.all(np.abs(p[0] - p[-1]) <= tol))


def rotate_ring_to_extreme(p: np.ndarray) -> np.ndarray:
    """A closed ring re-started at its lowest-x (then lowest-y) vertex, a convex-hull corner.

    Simplification keeps a ring's first vertex; starting at an extreme vertex keeps that
    vertex a genuine corner instead of a point in the middle of a straight side.
    """
    ring = p[:-1]
    k = int(np.lexsort((ring[:, 1], ring[:, 0]))[0])
    r = np.roll(ring, -k, axis=0)
    return np.vstack([r, r[:1]])


def polyline_length(p: np.ndarray) -> float:
    """Length (sum of edge lengths) of a ``(k, 2)`` polyline, same units as ``p``."""
    d = np.diff(p, axis=0)
    return float(np.sum(np.hypot(d[:, 0], d[:, 1])))


def simplify_polylines(polylines: list[np.ndarray], tolerance: float) -> list[np.ndarray]:
    """Douglas-Peucker simplification of each polyline to ``tolerance`` (same units).

    Every vertex dropped lies within ``tolerance`` of the simplified polyline. Closed rings
    are re-started at an extreme vertex first (:func:`rotate_ring_to_extreme`) and stay
    closed; a ring that collapses to fewer than 4 vertices is returned as its unsimplified
    self. End points of open polylines are kept; polylines of fewer than 3 vertices pass
    through unchanged.
    """
    import shapely

    out = [np.asarray(p, dtype=np.float64) for p in polylines]
    todo = [i for i, p in enumerate(out) if p.shape[0] >= 3]
    if not todo:
        return out
    prepared = [rotate_ring_to_extreme(out[i]) if is_closed(out[i]) else out[i] for i in todo]
    geoms = shapely.linestrings(
        np.concatenate(prepared),
        indices=np.repeat(np.arange(len(prepared)), [len(p) for p in prepared]),
    )
    simp = shapely.simplify(geoms, tolerance, preserve_topology=False)
    for i, orig, g in zip(todo, prepared, simp, strict=True):
        q = shapely.get_coordinates(g)
        if is_closed(orig) and q.shape[0] < 4:
            q = orig
        if q.shape[0] < 2:
            q = orig[[0, -1]]
        out[i] = np.asarray(q, dtype=np.float64)
    return out


def dedupe(p: np.ndarray) -> np.ndarray:
    """The polyline ``(k, 2)`` without consecutive duplicate vertices."""
    if p.shape[0] < 2:
        return p
    keep = np.ones(p.shape[0], dtype=bool)
    keep[1:] = np.any(np.diff(p, axis=0) != 0.0, axis=1)
    return p[keep]


def _end_direction(p: np.ndarray, at_end: bool, window: float) -> np.ndarray:
    """Unit vector pointing out of the polyline at its last (``at_end``) or first vertex,
    from the vertex ``window`` metres of arc length inward."""
    q = p if at_end else p[::-1]
    seg = np.hypot(*np.diff(q, axis=0).T)
    back = np.cumsum(seg[::-1])  # arc length from the end back to vertex -2, -3, ...
    j = int(np.searchsorted(back, window))
    j = min(j, q.shape[0] - 2)
    v = q[-1] - q[-2 - j]
    n = math.hypot(v[0], v[1])
    return v / n if n > 0.0 else np.zeros(2)


def join_polylines(
    polylines: list[np.ndarray],
    *,
    max_gap: float,
    max_angle: float,
    snap: float,
    end_window: float,
) -> list[np.ndarray]:
    """Join open polylines end to end where their ends face each other.

    Two ends (of different polylines) are joined when they are at most ``snap`` apart
    (whatever their directions), or at most ``max_gap`` apart with their outward directions
    opposite within ``max_angle`` degrees and each pointing along the gap within
    ``max_angle`` degrees. An end's outward direction is measured from the vertex
    ``end_window`` back along the polyline (same units as the coordinates). Pairs are taken
    greedily by increasing gap, each end at most once, never closing a loop. Closed polylines
    pass through unchanged; joined chains come after them, in order of their first member.
    Deterministic.
    """
    polys = polylines
    open_idx = [i for i, p in enumerate(polys) if not is_closed(p)]
    if not open_idx:
        return polys
    ends = []  # (polyline, at_end)
    pts = []
    dirs = []
    for i in open_idx:
        for at_end in (False, True):
            ends.append((i, at_end))
            pts.append(polys[i][-1] if at_end else polys[i][0])
            dirs.append(_end_direction(polys[i], at_end, end_window))
    P = np.asarray(pts)
    Dv = np.asarray(dirs)
    reach = max(max_gap, snap)
    pairs = cKDTree(P).query_pairs(reach, output_type="ndarray")
    cos_max = math.cos(math.radians(max_angle))
    cands = []
    for a, b in pairs.tolist():
        ia, ib = ends[a][0], ends[b][0]
        if ia == ib:
            continue
        gap_vec = P[b] - P[a]
        gap = math.hypot(gap_vec[0], gap_vec[1])
        if gap > snap:
            if -numeric.dot(Dv[a], Dv[b]) < cos_max:  # ends must point at each other
                continue
            u = gap_vec / gap
            if numeric.dot(Dv[a], u) < cos_max or -numeric.dot(Dv[b], u) < cos_max:
                continue
        cands.append((gap, a, b))
    cands.sort()
    partner = [-1] * len(ends)
    # union-find over polylines to avoid closing chains into loops accidentally
    parent = list(range(len(polys)))

    def find(x: int) -> int:
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    for _, a, b in cands:
        if partner[a] >= 0 or partner[b] >= 0:
            continue
        ra, rb = find(ends[a][0]), find(ends[b][0])
        if ra == rb:
            continue  # would close a loop; leave it open
        partner[a], partner[b] = b, a
        parent[ra] = rb
    if all(x < 0 for x in partner):
        return polys
    end_index = {e: k for k, e in enumerate(ends)}
    used = [False] * len(polys)
    is_open = set(open_idx)
    out: list[np.ndarray] = [polys[i] for i in range(len(polys)) if i not in is_open]
    for i in open_idx:
        if used[i]:
            continue
        # walk to the chain's start: follow the partner of the start end backwards
        cur, cur_start_end = i, False  # we enter polyline cur through its "start" end
        seen = {i}
        while True:
            k = end_index[(cur, cur_start_end)]
            if partner[k] < 0:
                break
            nxt_poly, nxt_at_end = ends[partner[k]]
            if nxt_poly in seen:
                break
            seen.add(nxt_poly)
            cur, cur_start_end = nxt_poly, not nxt_at_end
        # now walk forward from (cur, entering at cur_start_end)
        parts = []
        enter_at_end = cur_start_end
        while True:
            used[cur] = True
            q = polys[cur][::-1] if enter_at_end else polys[cur]
            parts.append(q)
            exit_key = end_index[(cur, not enter_at_end)]
            if partner[exit_key] < 0:
                break
            nxt_poly, nxt_at_end = ends[partner[exit_key]]
            if used[nxt_poly]:
                break
            cur, enter_at_end = nxt_poly, nxt_at_end
        out.append(dedupe(np.vstack(parts)))
    return out
