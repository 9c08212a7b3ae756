"""Compiled kernels of the map model and the precise fit (implementation details, numba).

Each kernel serves one public function: :func:`segment_grid` builds
:class:`service.core.sensor.mapmodel.MapModel`'s bucket grid, :func:`nearest_segments` answers
:meth:`~service.core.sensor.mapmodel.MapModel.nearest`, :func:`refine_iterations` is the loop of
:func:`service.core.sensor.refine.refine_pose`. The numpy references live beside their public
functions and tests compare both. Without numba (``kernels.HAVE_NUMBA`` false) the
references run.
"""

from __future__ import annotations

import math

import numpy as np

from service.core.kernels import njit, solve3, wrap


@njit(cache=True, nogil=True)
def segment_grid(
    segs: np.ndarray, x0: float, y0: float, nx: int, ny: int, cell: float, reach: float
) -> tuple[np.ndarray, np.ndarray]:
    """CSR lists of the segments within ``reach`` of each cell (conservatively: segment to
    cell-centre distance <= reach + half the cell diagonal). Cell ``(ix, iy)`` has index
    ``ix * ny + iy``. Returns ``(start (nx * ny + 1,), items)``."""
    S = segs.shape[0]
    pad = reach + 0.7072 * cell
    pad2 = pad * pad
    count = np.zeros(nx * ny + 1, dtype=np.intp)
    for p in range(2):
        if p == 1:
            start = np.cumsum(count)
            fill = start[:-1].copy()
            items = np.empty(start[-1], dtype=np.intp)
        for s in range(S):
            ax = segs[s, 0]
            ay = segs[s, 1]
            ex = segs[s, 2] - ax
            ey = segs[s, 3] - ay
            ee = ex * ex + ey * ey
            if ee < 1e-18:
                ee = 1e-18
            lox = math.floor((min(ax, ax + ex) - pad - x0) / cell)
            hix = math.floor((max(ax, ax + ex) + pad - x0) / cell)
            loy = math.floor((min(ay, ay + ey) - pad - y0) / cell)
            hiy = math.floor((max(ay, ay + ey) + pad - y0) / cell)
            for ix in range(max(lox, 0), min(hix, nx - 1) + 1):
                cx = x0 + (ix + 0.5) * cell
                for iy in range(max(loy, 0), min(hiy, ny - 1) + 1):
                    cy = y0 + (iy + 0.5) * cell
                    u = ((cx - ax) * ex + (cy - ay) * ey) / ee
                    if u < 0.0:
                        u = 0.0
                    elif u > 1.0:
                        u = 1.0
                    dx = cx - ax - u * ex
                    dy = cy - ay - u * ey
                    if dx * dx + dy * dy <= pad2:
                        c = ix * ny + iy
                        if p == 0:
                            count[c + 1] += 1
                        else:
                            items[fill[c]] = s
                            fill[c] += 1
    return start, items


@njit(cache=True, nogil=True)
def _nearest_one(
    qx: float,
    qy: float,
    nqx: float,
    nqy: float,
    segs: np.ndarray,
    snorm: np.ndarray,
    x0: float,
    y0: float,
    nx: int,
    ny: int,
    cell: float,
    start: np.ndarray,
    items: np.ndarray,
    max_dist: float,
    cos_gate: float,
) -> tuple[int, float, float, float, float, float]:
    """Nearest segment to ``(qx, qy)`` within ``max_dist`` whose normal is within the gate of
    the point's normal ``(nqx, nqy)`` (NaN normal: any). Returns ``(seg or -1, dist, foot x,
    foot y, normal x, normal y)``; the normal is the segment's, or the foot->point direction
    where the foot is clamped to an end."""
    fx = (qx - x0) / cell
    fy = (qy - y0) / cell
    if fx < 0.0 or fy < 0.0 or fx >= nx or fy >= ny:
        return -1, np.inf, 0.0, 0.0, 0.0, 0.0
    c = int(fx) * ny + int(fy)
    best = max_dist * max_dist
    bj = -1
    bu = 0.0
    use_n = nqx == nqx  # not NaN
    for t in range(start[c], start[c + 1]):
        j = items[t]
        if use_n and abs(nqx * snorm[j, 0] + nqy * snorm[j, 1]) < cos_gate:
            continue
        ax = segs[j, 0]
        ay = segs[j, 1]
        ex = segs[j, 2] - ax
        ey = segs[j, 3] - ay
        ee = ex * ex + ey * ey
        if ee < 1e-18:
            ee = 1e-18
        u = ((qx - ax) * ex + (qy - ay) * ey) / ee
        if u < 0.0:
            u = 0.0
        elif u > 1.0:
            u = 1.0
        dx = qx - ax - u * ex
        dy = qy - ay - u * ey
        d2 = dx * dx + dy * dy
        if d2 < best:
            best = d2
            bj = j
            bu = u
    if bj < 0:
        return -1, np.inf, 0.0, 0.0, 0.0, 0.0
    ax = segs[bj, 0]
    ay = segs[bj, 1]
    footx = ax + bu * (segs[bj, 2] - ax)
    footy = ay + bu * (segs[bj, 3] - ay)
    d = math.sqrt(best)
    nxs = snorm[bj, 0]
    nys = snorm[bj, 1]
    if (bu <= 0.0 or bu >= 1.0) and d > 1e-12:
        nxs = (qx - footx) / d
        nys = (qy - footy) / d
    return bj, d, footx, footy, nxs, nys


@njit(cache=True, nogil=True)
def nearest_segments(
    q: np.ndarray,
    qn: np.ndarray,
    segs: np.ndarray,
    snorm: np.ndarray,
    x0: float,
    y0: float,
    nx: int,
    ny: int,
    cell: float,
    start: np.ndarray,
    items: np.ndarray,
    max_dist: float,
    cos_gate: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_nearest_one` for every point: ``(seg (n,), dist (n,), foot (n, 2), normal
    (n, 2))``; ``seg = -1`` and ``dist = inf`` where nothing is within ``max_dist``."""
    n = q.shape[0]
    seg = np.full(n, -1, dtype=np.intp)
    dist = np.full(n, np.inf)
    foot = np.zeros((n, 2))
    nrm = np.zeros((n, 2))
    for i in range(n):
        j, d, fx, fy, ax, ay = _nearest_one(
            q[i, 0],
            q[i, 1],
            qn[i, 0],
            qn[i, 1],
            segs,
            snorm,
            x0,
            y0,
            nx,
            ny,
            cell,
            start,
            items,
            max_dist,
            cos_gate,
        )
        seg[i] = j
        dist[i] = d
        foot[i, 0] = fx
        foot[i, 1] = fy
        nrm[i, 0] = ax
        nrm[i, 1] = ay
    return seg, dist, foot, nrm


@njit(cache=True, nogil=True)
def refine_iterations(
    pts: np.ndarray,
    pnorm: np.ndarray,
    pw: np.ndarray,
    segs: np.ndarray,
    snorm: np.ndarray,
    x0: float,
    y0: float,
    nx: int,
    ny: int,
    cell: float,
    start: np.ndarray,
    items: np.ndarray,
    init: np.ndarray,
    prior: np.ndarray,
    prior_info: np.ndarray,
    iterations: int,
    trim_initial: float,
    trim_final: float,
    trim_decay: float,
    scale: float,
    cos_gate: float,
    damping: float,
    tol: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Gauss-Newton point-to-line fit of ``pts`` (robot frame) to the map, re-associating
    every iteration (see :func:`service.core.sensor.refine.refine_pose` for the meaning).
    Returns ``(pose, H, residuals (n,), iterations)``: signed point-to-line residuals at the
    final pose (inf where nothing is within the final trim) and ``H`` the normal matrix of
    the points alone there."""
    n = pts.shape[0]
    pose = init.copy()
    trim = trim_initial
    it = 0
    H = np.zeros((3, 3))
    g = np.zeros(3)
    for it in range(1, iterations + 1):  # noqa: B007 (the count is returned)
        c = math.cos(pose[2])
        s = math.sin(pose[2])
        for a in range(3):
            g[a] = 0.0
            for b in range(3):
                H[a, b] = 0.0
        for i in range(n):
            px = pts[i, 0]
            py = pts[i, 1]
            qx = c * px - s * py + pose[0]
            qy = s * px + c * py + pose[1]
            nqx = c * pnorm[i, 0] - s * pnorm[i, 1]
            nqy = s * pnorm[i, 0] + c * pnorm[i, 1]
            j, _d, fx, fy, mx, my = _nearest_one(
                qx, qy, nqx, nqy, segs, snorm, x0, y0, nx, ny, cell, start, items, trim, cos_gate
            )
            if j < 0:
                continue
            r = mx * (qx - fx) + my * (qy - fy)
            jt = mx * (-(qy - pose[1])) + my * (qx - pose[0])
            w = pw[i] / (1.0 + (r / scale) * (r / scale))
            J0 = mx
            J1 = my
            J2 = jt
            H[0, 0] += w * J0 * J0
            H[0, 1] += w * J0 * J1
            H[0, 2] += w * J0 * J2
            H[1, 1] += w * J1 * J1
            H[1, 2] += w * J1 * J2
            H[2, 2] += w * J2 * J2
            g[0] += w * J0 * r
            g[1] += w * J1 * r
            g[2] += w * J2 * r
        H[1, 0] = H[0, 1]
        H[2, 0] = H[0, 2]
        H[2, 1] = H[1, 2]
        A = np.empty((3, 3))
        e = np.empty(3)
        e[0] = pose[0] - prior[0]
        e[1] = pose[1] - prior[1]
        e[2] = wrap(pose[2] - prior[2])
        tr = (H[0, 0] + H[1, 1] + H[2, 2]) / 3.0
        for a in range(3):
            for b in range(3):
                A[a, b] = H[a, b] + prior_info[a, b]
            A[a, a] += damping * tr + 1e-9
        b3 = np.empty(3)
        for a in range(3):
            b3[a] = -(
                g[a] + prior_info[a, 0] * e[0] + prior_info[a, 1] * e[1] + prior_info[a, 2] * e[2]
            )
        dx = solve3(A, b3)
        pose[0] += dx[0]
        pose[1] += dx[1]
        pose[2] = wrap(pose[2] + dx[2])
        trim = max(trim_final, trim * trim_decay)
        if abs(dx[0]) < tol and abs(dx[1]) < tol and abs(dx[2]) < tol and trim <= trim_final:
            break
    # final residuals and the normal matrix at the final pose
    c = math.cos(pose[2])
    s = math.sin(pose[2])
    for a in range(3):
        for b in range(3):
            H[a, b] = 0.0
    res = np.full(n, np.inf)
    for i in range(n):
        px = pts[i, 0]
        py = pts[i, 1]
        qx = c * px - s * py + pose[0]
        qy = s * px + c * py + pose[1]
        nqx = c * pnorm[i, 0] - s * pnorm[i, 1]
        nqy = s * pnorm[i, 0] + c * pnorm[i, 1]
        j, _d, fx, fy, mx, my = _nearest_one(
            qx, qy, nqx, nqy, segs, snorm, x0, y0, nx, ny, cell, start, items, trim, cos_gate
        )
        if j < 0:
            continue
        r = mx * (qx - fx) + my * (qy - fy)
        res[i] = r
        jt = mx * (-(qy - pose[1])) + my * (qx - pose[0])
        w = pw[i] / (1.0 + (r / scale) * (r / scale))
        H[0, 0] += w * mx * mx
        H[0, 1] += w * mx * my
        H[0, 2] += w * mx * jt
        H[1, 1] += w * my * my
        H[1, 2] += w * my * jt
        H[2, 2] += w * jt * jt
    H[1, 0] = H[0, 1]
    H[2, 0] = H[0, 2]
    H[2, 1] = H[1, 2]
    return pose, H, res, it


@njit(cache=True, nogil=True)
def scan_normals(
    points: np.ndarray, max_gap: float, gap_factor: float, cut: np.ndarray
) -> np.ndarray:
    """Kernel of :func:`service.core.refine.scan_normals` (same expressions): ``cut[i]``
    true where a new polyline begins at row ``i``."""
    n = points.shape[0]
    out = np.full((n, 2), np.nan)
    if n < 2:
        return out
    for i in range(n):
        lim = max_gap + gap_factor * np.hypot(points[i, 0], points[i, 1])
        prev_ok = (
            i > 0
            and not cut[i]
            and np.hypot(points[i, 0] - points[i - 1, 0], points[i, 1] - points[i - 1, 1]) <= lim
        )
        next_ok = (
            i < n - 1
            and not cut[i + 1]
            and np.hypot(points[i + 1, 0] - points[i, 0], points[i + 1, 1] - points[i, 1]) <= lim
        )
        if not (prev_ok or next_ok):
            continue
        j0 = i - 1 if prev_ok else i
        j1 = i + 1 if next_ok else i
        tx = points[j1, 0] - points[j0, 0]
        ty = points[j1, 1] - points[j0, 1]
        tn = np.hypot(tx, ty)
        if tn > 1e-9:
            out[i, 0] = -ty / tn
            out[i, 1] = tx / tn
    return out
