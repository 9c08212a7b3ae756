"""Compiled scan-to-scan fit of :mod:`service.core.tracking.scan_odometry` (implementation detail,
numba; conventions of :mod:`service.core.kernels`). The numpy reference is
:func:`service.core.tracking.scan_odometry._match_numpy`; both associate every point with the
*nearest* previous point within the gate whose surface normal agrees with the point's (here
through the buckets of :func:`service.core.kernels.grid.grid_build`, whose cell is the largest
gate; there among the KD-tree's 16 nearest), so both take the same steps up to ties,
rounding and crowds of more than 16 closer points with the wrong orientation.
"""

from __future__ import annotations

import math

import numpy as np

from service.core.kernels import njit, solve3


@njit(cache=True, nogil=True)
def _nearest(
    x: float,
    y: float,
    prev: np.ndarray,
    start: np.ndarray,
    items: np.ndarray,
    ox: float,
    oy: float,
    nx: int,
    ny: int,
    cell: float,
    gate: float,
    normals: np.ndarray,
    mx: float,
    my: float,
    cos_gate: float,
) -> int:
    """Index of the previous point nearest to ``(x, y)`` within ``gate`` whose normal lies
    within the normal gate of ``(mx, my)`` (either sign), -1 for none. The cells of
    :func:`service.core.kernels.grid.grid_build` are visited ring by ring from the point's
    own, skipping those farther than the nearest point found so far: on a scan's surfaces the
    nearest point is usually in the point's own cell, and the rings beyond it are skipped."""
    cx = math.floor((x - ox) / cell)
    cy = math.floor((y - oy) / cell)
    best = -1
    bd = gate * gate
    rings = math.ceil(gate / cell)
    for ring in range(rings + 1):
        lower = (ring - 1) * cell  # no cell of this ring is nearer to the point than this
        if ring >= 2 and lower * lower > bd:
            break
        for gx in range(cx - ring, cx + ring + 1):
            if gx < 0 or gx >= nx:
                continue
            side = gx == cx - ring or gx == cx + ring
            step = 1 if (side or ring == 0) else 2 * ring  # the ring's border cells only
            gy = cy - ring
            while gy <= cy + ring:
                if 0 <= gy < ny:
                    bx = ox + gx * cell
                    by = oy + gy * cell
                    dx = max(bx - x, 0.0, x - (bx + cell))
                    dy = max(by - y, 0.0, y - (by + cell))
                    if dx * dx + dy * dy <= bd:
                        k = gx * ny + gy
                        for m in range(start[k], start[k + 1]):
                            j = items[m]
                            ex = prev[j, 0] - x
                            ey = prev[j, 1] - y
                            d = ex * ex + ey * ey
                            agree = abs(normals[j, 0] * mx + normals[j, 1] * my) >= cos_gate
                            # of equal distances the higher index, whatever the visiting order
                            if agree and (d < bd or (d == bd and j > best)):
                                bd = d
                                best = j
                gy += step
    return best


@njit(cache=True, nogil=True)
def match_iterations(
    prev: np.ndarray,
    normals: np.ndarray,
    start: np.ndarray,
    items: np.ndarray,
    ox: float,
    oy: float,
    nx: int,
    ny: int,
    cell: float,
    points: np.ndarray,
    point_normals: np.ndarray,
    delta: np.ndarray,
    information: np.ndarray,
    cos_gate: float,
    iterations: int,
    gate0: float,
    gate1: float,
    robust: float,
    scale0: float,
    effective: float,
    tolerance: float,
) -> tuple[np.ndarray, float, np.ndarray, float]:
    """The Gauss-Newton loop of :func:`service.core.tracking.scan_odometry.match_increment`: returns
    the refined increment, the share of ``points`` within ``tolerance`` of the previous
    scan's surfaces at the end, and the last step's normal matrix of the points (3x3, robust
    weights, unscaled) with the sum of those weights."""
    x = delta.copy()
    n = points.shape[0]
    its = max(1, iterations)
    H = np.empty((3, 3))
    g = np.empty(3)
    for k in range(its):
        gate = gate0 + (gate1 - gate0) * k / max(1, its - 1)
        c = math.cos(x[2])
        s = math.sin(x[2])
        H[:, :] = 0.0
        g[:] = 0.0
        total = 0.0
        found = 0
        for i in range(n):
            rx = c * points[i, 0] - s * points[i, 1]
            ry = s * points[i, 0] + c * points[i, 1]
            qx = rx + x[0]
            qy = ry + x[1]
            mx = c * point_normals[i, 0] - s * point_normals[i, 1]
            my = s * point_normals[i, 0] + c * point_normals[i, 1]
            j = _nearest(
                qx, qy, prev, start, items, ox, oy, nx, ny, cell, gate, normals, mx, my, cos_gate
            )
            if j < 0:
                continue
            found += 1
            n0 = normals[j, 0]
            n1 = normals[j, 1]
            r = n0 * (qx - prev[j, 0]) + n1 * (qy - prev[j, 1])
            j2 = n1 * rx - n0 * ry
            w = 1.0 / (1.0 + (r / robust) ** 2)
            total += w
            jac = (n0, n1, j2)
            for a in range(3):
                g[a] += w * jac[a] * r
                for b in range(3):
                    H[a, b] += w * jac[a] * jac[b]
        if found == 0:
            return x, 0.0, H, 0.0
        scale = scale0
        if total > effective:
            scale = scale0 * effective / total
        e0 = x[0] - delta[0]
        e1 = x[1] - delta[1]
        e2 = (x[2] - delta[2] + math.pi) % (2.0 * math.pi) - math.pi
        A = np.empty((3, 3))
        rhs = np.empty(3)
        for a in range(3):
            rhs[a] = -(
                scale * g[a]
                + information[a, 0] * e0
                + information[a, 1] * e1
                + information[a, 2] * e2
            )
            for b in range(3):
                A[a, b] = scale * H[a, b] + information[a, b]
        # LU in LAPACK's order without LAPACK (whose kernels differ between CPUs); a singular
        # system (the reference's LinAlgError) ends the iterations
        step = solve3(A, rhs)
        if not (np.isfinite(step[0]) and np.isfinite(step[1]) and np.isfinite(step[2])):
            break
        x += step
        if math.hypot(step[0], step[1]) < 1e-4 and abs(step[2]) < 1e-5:
            break
    c = math.cos(x[2])
    s = math.sin(x[2])
    good = 0
    for i in range(n):
        qx = c * points[i, 0] - s * points[i, 1] + x[0]
        qy = s * points[i, 0] + c * points[i, 1] + x[1]
        mx = c * point_normals[i, 0] - s * point_normals[i, 1]
        my = s * point_normals[i, 0] + c * point_normals[i, 1]
        j = _nearest(
            qx, qy, prev, start, items, ox, oy, nx, ny, cell, gate1, normals, mx, my, cos_gate
        )
        if j < 0:
            continue
        r = normals[j, 0] * (qx - prev[j, 0]) + normals[j, 1] * (qy - prev[j, 1])
        if abs(r) <= tolerance:
            good += 1
    return x, good / n, H, total


@njit(cache=True, nogil=True)
def surface_normals(
    p: np.ndarray, half_window: int, radius: float, max_flatness: float
) -> np.ndarray:
    """:func:`service.core.tracking.scan_odometry.surface_normals` (same expressions)."""
    n = p.shape[0]
    out = np.full((n, 2), np.nan)
    if n < 3:
        return out
    h = max(1, half_window)
    r2 = radius * radius
    for i in range(n):
        cnt = 0
        mx = 0.0
        my = 0.0
        for j in range(max(0, i - h), min(n, i + h + 1)):
            dx = p[j, 0] - p[i, 0]
            dy = p[j, 1] - p[i, 1]
            if dx * dx + dy * dy <= r2:
                cnt += 1
                mx += p[j, 0]
                my += p[j, 1]
        if cnt < 3:
            continue
        mx /= cnt
        my /= cnt
        sxx = 0.0
        syy = 0.0
        sxy = 0.0
        for j in range(max(0, i - h), min(n, i + h + 1)):
            dx = p[j, 0] - p[i, 0]
            dy = p[j, 1] - p[i, 1]
            if dx * dx + dy * dy <= r2:
                cx = p[j, 0] - mx
                cy = p[j, 1] - my
                sxx += cx * cx
                syy += cy * cy
                sxy += cx * cy
        half = 0.5 * (sxx + syy)
        root = math.sqrt(max(0.25 * (sxx - syy) ** 2 + sxy * sxy, 0.0))
        small = half - root
        large = half + root
        if large > 0 and small <= max_flatness * large:
            angle = 0.5 * math.atan2(2.0 * sxy, sxx - syy)
            out[i, 0] = -math.sin(angle)
            out[i, 1] = math.cos(angle)
    return out
