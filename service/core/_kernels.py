"""Compiled inner loops of the shape-based localiser (implementation details, numba).

Each kernel is a plain function over float64 / intp arrays, called by exactly one public
function that owns the concept and its docstring (:func:`service.core.similarity.shape_distance`,
:func:`service.core.dce.dce`, ...; the pose fits' kernels are in
:mod:`service.core._pose_kernels`, which shares ``_solve3`` and ``_wrap`` from here). The
arithmetic follows the numpy reference
implementations expression by expression (no ``fastmath``), so results agree with them to the
last bits except where a libm call differs; tests compare both on random inputs.

numba is optional: without it (``HAVE_NUMBA`` is ``False``) the callers run their numpy
reference code. Kernels are compiled with ``cache=True`` (on-disk cache next to this file, or
under ``NUMBA_CACHE_DIR``), so a fresh process loads them instead of compiling.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

try:  # pragma: no cover - exercised by whichever environment runs the tests
    from numba import njit

    HAVE_NUMBA = True
except ImportError:  # pragma: no cover
    HAVE_NUMBA = False

    def njit(*_args: Any, **_kwargs: Any) -> Any:  # type: ignore[no-redef]
        def deco(fn: Any) -> Any:
            return fn

        return deco


_TWO_PI = 2.0 * math.pi


@njit(cache=True, nogil=True)
def _wrap(a: float) -> float:
    """(-pi, pi] like :func:`service.core.types.wrap_angle`."""
    return math.pi - ((math.pi - a) % _TWO_PI)


@njit(cache=True, nogil=True)
def _solve3(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``A x = b`` for a 3x3 ``A``: LU with partial pivoting in LAPACK's order (dgetf2 +
    dgetrs), without the per-call overhead of ``np.linalg.solve``. ``A`` is overwritten."""
    x = b.copy()
    _solve3_into(A, x)
    return x


@njit(cache=True, nogil=True)
def _solve3_into(A: np.ndarray, x: np.ndarray) -> None:
    """:func:`_solve3` in place: ``x`` holds ``b`` on entry and the solution on return."""
    for j in range(3):
        p = j
        big = abs(A[j, j])
        for i in range(j + 1, 3):
            if abs(A[i, j]) > big:
                big = abs(A[i, j])
                p = i
        if p != j:
            for k in range(3):
                t = A[j, k]
                A[j, k] = A[p, k]
                A[p, k] = t
            t = x[j]
            x[j] = x[p]
            x[p] = t
        if A[j, j] != 0.0:
            r = 1.0 / A[j, j]
            for i in range(j + 1, 3):
                A[i, j] *= r
        for i in range(j + 1, 3):
            for k in range(j + 1, 3):
                A[i, k] -= A[i, j] * A[j, k]
    for k in range(3):  # L y = b (unit lower)
        if x[k] != 0.0:
            for i in range(k + 1, 3):
                x[i] -= x[k] * A[i, k]
    for k in range(2, -1, -1):  # U x = y
        if x[k] != 0.0:
            x[k] /= A[k, k]
            for i in range(k):
                x[i] -= x[k] * A[i, k]


@njit(cache=True, nogil=True)
def angular_intervals(points: np.ndarray, offsets: np.ndarray, viewpoint: np.ndarray) -> np.ndarray:
    """Kernel of :func:`service.core.matching.map_order`: per polyline ``f`` (rows
    ``offsets[f] .. offsets[f + 1] - 1`` of ``points``) the ``(start, span)`` of its bearings
    seen from ``viewpoint`` ``[x, y, theta]``, exactly as ``matching._angular_interval``."""
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
            cum += ((b - prev) + math.pi) % _TWO_PI - math.pi
            if cum < lo:
                lo = cum
            if cum > hi:
                hi = cum
            prev = b
        out[f, 0] = _wrap(b0 + lo)
        out[f, 1] = hi - lo
    return out


@njit(cache=True, nogil=True)
def arc_tables(
    p: np.ndarray, max_merge: int
) -> tuple[int, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Kernel of :class:`service.core.similarity.ShapeArcs`: drop repeated vertices of ``p``
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
    """Kernel of S* (:func:`service.core.similarity._dp`, same states, moves, order and
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


@njit(cache=True, nogil=True)
def _rel_less(rel: np.ndarray, a: int, b: int) -> bool:
    """DCE's removal order: lower relevance first, ties by lower vertex index."""
    return rel[a] < rel[b] or (rel[a] == rel[b] and a < b)


@njit(cache=True, nogil=True)
def _sift_up(heap: np.ndarray, pos: np.ndarray, rel: np.ndarray, c: int) -> None:
    v = heap[c]
    while c > 0:
        par = (c - 1) // 2
        pv = heap[par]
        if not _rel_less(rel, v, pv):
            break
        heap[c] = pv
        pos[pv] = c
        c = par
    heap[c] = v
    pos[v] = c


@njit(cache=True, nogil=True)
def _sift_down(heap: np.ndarray, pos: np.ndarray, rel: np.ndarray, c: int, n: int) -> None:
    v = heap[c]
    while True:
        m = 2 * c + 1
        if m >= n:
            break
        if m + 1 < n and _rel_less(rel, heap[m + 1], heap[m]):
            m += 1
        mv = heap[m]
        if not _rel_less(rel, mv, v):
            break
        heap[c] = mv
        pos[mv] = c
        c = m
    heap[c] = v
    pos[v] = c


@njit(cache=True, nogil=True)
def dce_kept(p: np.ndarray, threshold: float) -> np.ndarray:
    """Kernel of :func:`service.core.dce.dce`: fixed-threshold DCE (eq. 2) of ``p`` ``(k, 2)``
    with the same removal order as :class:`service.core.dce.CurveEvolution` (least relevance
    first, ties by lower index). Returns the kept vertex indices, sorted.

    The interior vertices sit in a binary heap indexed by vertex (a neighbour's new
    relevance moves it in place); ``el[v]`` keeps the length of the edge from ``v`` to its
    next kept vertex, computed once as ``hypot(x[next] - x[v], y[next] - y[v])``, the same
    expression each relevance uses."""
    k = p.shape[0]
    x = p[:, 0]
    y = p[:, 1]
    prev = np.arange(-1, k - 1)
    nxt = np.arange(1, k + 1)
    rel = np.full(k, np.inf)
    el = np.empty(k)
    for i in range(k - 1):
        el[i] = math.hypot(x[i + 1] - x[i], y[i + 1] - y[i])
    heap = np.empty(k, dtype=np.intp)
    pos = np.full(k, -1, dtype=np.intp)
    n = 0
    for i in range(1, k - 1):
        rel[i] = el[i - 1] + el[i] - math.hypot(x[i + 1] - x[i - 1], y[i + 1] - y[i - 1])
        heap[n] = i
        n += 1
        _sift_up(heap, pos, rel, n - 1)
    last = k - 1
    removed = 0
    while n > 0:
        i = heap[0]
        if rel[i] >= threshold:
            break
        n -= 1
        if n > 0:
            heap[0] = heap[n]
            _sift_down(heap, pos, rel, 0, n)
        removed += 1
        u = prev[i]
        w = nxt[i]
        nxt[u] = w
        prev[w] = u
        xu = x[u]
        yu = y[u]
        xw = x[w]
        yw = y[w]
        duw = math.hypot(xw - xu, yw - yu)
        el[u] = duw
        if u > 0:
            old = rel[u]
            uu = prev[u]
            rel[u] = el[uu] + duw - math.hypot(xw - x[uu], yw - y[uu])
            if rel[u] < old:
                _sift_up(heap, pos, rel, pos[u])
            else:
                _sift_down(heap, pos, rel, pos[u], n)
        if w < last:
            old = rel[w]
            ww = nxt[w]
            rel[w] = duw + el[w] - math.hypot(x[ww] - xu, y[ww] - yu)
            if rel[w] < old:
                _sift_up(heap, pos, rel, pos[w])
            else:
                _sift_down(heap, pos, rel, pos[w], n)
    out = np.empty(k - removed, dtype=np.intp)
    j = 0
    i = 0
    while True:
        out[j] = i
        j += 1
        if i == last:
            break
        i = nxt[i]
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
    """Kernel of :func:`service.core.matching.order_preserving_dp` (eq. 5), same recurrence
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


@njit(cache=True, nogil=True)
def grid_build(
    pts: np.ndarray, cell: float
) -> tuple[float, float, int, int, np.ndarray, np.ndarray]:
    """Bucket ``pts`` ``(N, 2)`` into a dense grid of ``cell``-sized squares (CSR layout).
    Returns ``(x0, y0, nx, ny, start (nx * ny + 1,), order (N,))``."""
    n = pts.shape[0]
    x0 = np.inf
    y0 = np.inf
    x1 = -np.inf
    y1 = -np.inf
    for i in range(n):
        x0 = min(x0, pts[i, 0])
        y0 = min(y0, pts[i, 1])
        x1 = max(x1, pts[i, 0])
        y1 = max(y1, pts[i, 1])
    nx = int((x1 - x0) / cell) + 1
    ny = int((y1 - y0) / cell) + 1
    cid = np.empty(n, dtype=np.intp)
    count = np.zeros(nx * ny + 1, dtype=np.intp)
    for i in range(n):
        cx = min(int((pts[i, 0] - x0) / cell), nx - 1)
        cy = min(int((pts[i, 1] - y0) / cell), ny - 1)
        cid[i] = cx * ny + cy
        count[cid[i] + 1] += 1
    start = np.cumsum(count)
    fill = start[:-1].copy()
    order = np.empty(n, dtype=np.intp)
    for i in range(n):
        order[fill[cid[i]]] = i
        fill[cid[i]] += 1
    return x0, y0, nx, ny, start, order


@njit(cache=True, nogil=True)
def grid_near(
    sx: np.ndarray,
    sy: np.ndarray,
    x0: float,
    y0: float,
    nx: int,
    ny: int,
    start: np.ndarray,
    cell: float,
    qx: np.ndarray,
    qy: np.ndarray,
    tol: float,
) -> np.ndarray:
    """Per query point ``(qx[i], qy[i])``: is some grid point closer than ``tol`` (<= ``cell``)?
    ``sx``, ``sy``: the grid's points in cell order (``pts[order]`` of :func:`grid_build`), so
    the 3 cells of a column of the 3 x 3 neighbourhood are one run. Exact (all points of the
    3 x 3 neighbouring cells are tested)."""
    n = qx.shape[0]
    out = np.zeros(n, dtype=np.bool_)
    t2 = tol * tol
    for i in range(n):
        xi = qx[i]
        yi = qy[i]
        fx = (xi - x0) / cell
        fy = (yi - y0) / cell
        if fx < -1.0 or fy < -1.0 or fx >= nx + 1.0 or fy >= ny + 1.0:
            continue
        cx = math.floor(fx)
        cy = math.floor(fy)
        lo = max(cy - 1, 0)
        hi = min(cy + 2, ny)
        if lo >= hi:
            continue
        found = False
        for ax in range(max(cx - 1, 0), min(cx + 2, nx)):
            for t in range(start[ax * ny + lo], start[ax * ny + hi]):
                dx = sx[t] - xi
                dy = sy[t] - yi
                if dx * dx + dy * dy < t2:
                    found = True
                    break
            if found:
                break
        out[i] = found
    return out


@njit(cache=True, nogil=True)
def nearest_segment(points: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """Kernel of :func:`service.core.configuration._hit_segments`: index of the segment
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


def warm_up() -> float:
    """Compile (first run after an install or a change of this file, ~10 s) or load from the
    on-disk cache (~0.3 s) every kernel, on tiny inputs; returns the seconds taken. Call it
    once at image build / install time so that services and tests start warm."""
    import time

    t0 = time.perf_counter()
    if not HAVE_NUMBA:
        return 0.0
    p = np.array([[0.0, 0.0], [1.0, 0.1], [2.0, 0.0], [2.0, 1.0]])
    segs = np.array([[0.0, -0.1, 2.0, -0.1], [2.1, -0.1, 2.1, 1.0]])
    own = np.zeros(4, dtype=np.intp)
    z = np.zeros(1, dtype=np.intp)
    two = np.array([2], dtype=np.intp)
    from service.core import _pose_kernels

    _pose_kernels.fit_blocks(
        p, np.arange(4), z, np.array([4]), segs, z, two, np.zeros((1, 3)), 2, 0.1, 0.05
    )
    block_candidates(np.ones((2, 2), dtype=np.bool_), 3, True)
    range_means(p, z, np.array([4]))
    _pose_kernels.pose_iterations(
        p, own, segs, z, two, np.zeros(3), 2, 0.3, 0.05, 1e-3, 1e-6, np.zeros(3), 0.0
    )
    angular_intervals(p, np.array([0, 4], dtype=np.intp), np.zeros(3))
    _, _, _, cum, tab = arc_tables(p, 4)
    shape_dp(cum, tab, cum, tab, 4, 4, 0.1, 0.5, np.inf)
    # the batch kernels of the shape matching and the extraction (their modules import this one)
    from service.core import _shape_kernels

    whole = np.array([[0, -1]], dtype=np.intp)
    off = np.array([0, 4], dtype=np.intp)
    _shape_kernels.shape_distances(p, off, whole, p, off, whole, 4, 0.1, 0.5, 1.0)
    _shape_kernels.piece_means(p, off, whole)
    _shape_kernels.interval_gates(np.zeros((1, 2)), np.ones((2, 2)), 0.1, -1.0, 1.0)
    _shape_kernels.block_pieces(np.zeros((1, 4), dtype=np.intp), z, 3, 2)
    _shape_kernels.order_dp_blocks(np.ones(1), np.ones(1), z, z, z, z, np.ones(1))
    from service.core import _extract_kernels

    _extract_kernels.simplify_groups(p, off, 0.04, 1.5)
    dce_kept(p, 0.04)
    cell = np.array([0, 0, 1], dtype=np.intp)
    order_dp(np.ones(1), np.ones(1), cell, z, z, np.ones(1))
    x0, y0, nx, ny, start, order = grid_build(p, 0.1)
    sx, sy = p[order, 0].copy(), p[order, 1].copy()
    grid_near(sx, sy, x0, y0, nx, ny, start, 0.1, p[:, 0].copy(), p[:, 1].copy(), 0.1)
    nearest_segment(p, segs)
    split_cuts(np.array([0, 3], dtype=np.intp), p, 1.5)
    from service.core import _search_kernels

    _search_kernels.warm_up(p)
    from service.core import _raycast_kernels

    _raycast_kernels.warm_up()
    # the map model's kernels (service.core._map_kernels; imported here, not at module level,
    # because that module imports this one)
    from service.core.mapmodel import MapModel
    from service.core.refine import RefineParams, refine_pose
    from service.core.types import MapData

    model = MapModel(MapData.from_lists("warm-up", "metric", [p]))
    refine_pose(model, p, np.zeros(3), RefineParams(iterations=2))
    model.nearest(p, 0.5, np.full_like(p, np.nan))
    # the scan-to-scan fit of the odometry check (service.core._odometry_kernels)
    from service.core.motion import MotionConfig
    from service.core.scan_odometry import ScanOdometry

    check = ScanOdometry(MotionConfig().scan_odometry, MotionConfig())
    beams = np.linspace(-1.5, 1.5, 40)
    wall = 1.0 / np.maximum(np.cos(beams), 0.2)
    check.correct(wall, beams, np.zeros(3))
    check.correct(wall, beams, np.array([0.01, 0.0, 0.0]))
    return time.perf_counter() - t0


@njit(cache=True, nogil=True)
def split_cuts(
    keep: np.ndarray, points: np.ndarray, piece_length: float
) -> tuple[bool, np.ndarray, np.ndarray]:
    """Kernel of :func:`service.core.configuration.split_pieces` (same arithmetic). Returns
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
def block_candidates(single: np.ndarray, K: int, join_total: bool) -> np.ndarray:
    """Kernel of the candidate blocks of :func:`service.core.matching.match_with_cost`:
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
