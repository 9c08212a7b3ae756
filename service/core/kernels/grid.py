"""Compiled bucket grid of points (implementation details, numba; the conventions of
:mod:`service.core.kernels`).

:func:`grid_build` buckets points into a dense grid of square cells (CSR layout) and
:func:`grid_near` tells exactly, in place of a KD-tree query, whether some grid point lies
closer than a tolerance: both for :func:`service.core.shapes.two_step._near` (the support and the
heading sweep of the two-step matching). The scan-to-scan fit of
:mod:`service.core.tracking.scan_odometry` buckets the previous scan with :func:`grid_build` too
(searched by :mod:`service.core.kernels.odometry`).
"""

from __future__ import annotations

import math

import numpy as np

from service.core.kernels import njit


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


def warm_up() -> None:
    """Compile (or load) this module's kernels on tiny inputs."""
    p = np.array([[0.0, 0.0], [1.0, 0.1], [2.0, 0.0], [2.0, 1.0]])
    x0, y0, nx, ny, start, order = grid_build(p, 0.1)
    sx, sy = p[order, 0].copy(), p[order, 1].copy()
    grid_near(sx, sy, x0, y0, nx, ny, start, 0.1, p[:, 0].copy(), p[:, 1].copy(), 0.1)
