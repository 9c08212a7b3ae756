"""Raster helpers: occupancy grids over one room, clearance, connectivity and grid paths.

A :class:`Grid` covers an axis-aligned area with square cells of ``h`` metres (map frame); cell
``(i, j)`` has its centre at ``(x0 + (j + 0.5) h, y0 + (i + 0.5) h)``. Clearances derived from
it are conservative: the exact distance of a cell centre to the nearest obstacle is at least
the value reported (the distance transform runs between cell centres; ``h / sqrt(2)`` is
subtracted for the half cell of the obstacle).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import shapely
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

_SQ2 = float(np.sqrt(2.0))


@dataclass
class Grid:
    """Cells over ``[x0, x0 + nx h] x [y0, y0 + ny h]``; ``free`` is ``(ny, nx)`` bool."""

    x0: float
    y0: float
    h: float
    free: np.ndarray

    @staticmethod
    def over(bounds: tuple[float, float, float, float], h: float) -> Grid:
        """An all-obstacle grid covering ``bounds`` ``(xmin, ymin, xmax, ymax)``."""
        nx = max(1, int(np.ceil((bounds[2] - bounds[0]) / h)))
        ny = max(1, int(np.ceil((bounds[3] - bounds[1]) / h)))
        return Grid(float(bounds[0]), float(bounds[1]), h, np.zeros((ny, nx), bool))

    @property
    def shape(self) -> tuple[int, int]:
        return self.free.shape  # type: ignore[return-value]

    def centers(self, i: np.ndarray, j: np.ndarray) -> np.ndarray:
        """Map-frame centres ``(n, 2)`` of cells ``(i, j)``."""
        return np.c_[
            self.x0 + (np.asarray(j) + 0.5) * self.h, self.y0 + (np.asarray(i) + 0.5) * self.h
        ]

    def cell(self, p: np.ndarray) -> tuple[int, int]:
        """The cell ``(i, j)`` holding point ``p`` (clipped to the grid)."""
        ny, nx = self.shape
        j = int(np.clip((p[0] - self.x0) // self.h, 0, nx - 1))
        i = int(np.clip((p[1] - self.y0) // self.h, 0, ny - 1))
        return i, j

    def mask(self, geom: object) -> np.ndarray:
        """``(ny, nx)`` bool: cells whose centre lies in ``geom`` (any shapely geometry)."""
        out = np.zeros(self.shape, bool)
        if geom is None or shapely.is_empty(geom):
            return out
        xmin, ymin, xmax, ymax = shapely.bounds(geom)
        ny, nx = self.shape
        j0 = max(0, int(np.floor((xmin - self.x0) / self.h - 0.5)))
        j1 = min(nx, int(np.ceil((xmax - self.x0) / self.h + 0.5)))
        i0 = max(0, int(np.floor((ymin - self.y0) / self.h - 0.5)))
        i1 = min(ny, int(np.ceil((ymax - self.y0) / self.h + 0.5)))
        if j1 <= j0 or i1 <= i0:
            return out
        jj, ii = np.meshgrid(np.arange(j0, j1), np.arange(i0, i1))
        xs = self.x0 + (jj + 0.5) * self.h
        ys = self.y0 + (ii + 0.5) * self.h
        out[i0:i1, j0:j1] = shapely.contains_xy(geom, xs, ys)
        return out

    def clearance(self, free: np.ndarray | None = None) -> np.ndarray:
        """Conservative distance (m) of every cell centre to the nearest non-free cell or the
        grid border (0 on obstacles)."""
        f = self.free if free is None else free
        padded = np.pad(f, 1, constant_values=False)
        d = ndimage.distance_transform_edt(padded)[1:-1, 1:-1] * self.h
        return np.where(f, np.maximum(d - self.h / _SQ2, 0.0), 0.0)


def main_component_share(ok: np.ndarray, seeds: list[tuple[int, int]]) -> float:
    """Share of the ``ok`` cells in the 8-connected component holding every seed cell; 0 if
    the seeds are not all in one component (or a seed is not ``ok``)."""
    if not ok.any():
        return 0.0
    lab, _ = ndimage.label(ok, structure=np.ones((3, 3), bool))
    ids = {int(lab[s]) for s in seeds}
    if not seeds or len(ids) != 1 or 0 in ids:
        return 0.0
    return float(np.count_nonzero(lab == ids.pop()) / np.count_nonzero(ok))


class GridPlanner:
    """Shortest paths over cells with clearance >= ``c_min`` (m); a cell with clearance below
    ``c_pref`` costs up to ``1 + weight`` times its length, which keeps paths centred."""

    def __init__(self, grid: Grid, clear: np.ndarray, c_min: float, c_pref: float, weight=3.0):
        self.grid = grid
        self.clear = clear
        ok = clear >= c_min
        ny, nx = ok.shape
        idx = -np.ones(ok.shape, np.int64)
        idx[ok] = np.arange(int(ok.sum()))
        self.idx = idx
        self.cells = np.argwhere(ok)
        pen = 1.0 + weight * np.clip((c_pref - clear) / max(c_pref - c_min, 1e-9), 0.0, 1.0)
        rows, cols, vals = [], [], []
        for di, dj, ln in ((0, 1, 1.0), (1, 0, 1.0), (1, 1, _SQ2), (1, -1, _SQ2)):
            sa = (slice(0, ny - di), slice(max(0, -dj), nx - max(0, dj)))
            sb = (slice(di, ny), slice(max(0, dj), nx - max(0, -dj)))
            ia, ib = idx[sa], idx[sb]
            m = (ia >= 0) & (ib >= 0)
            rows.append(ia[m])
            cols.append(ib[m])
            vals.append(ln * grid.h * 0.5 * (pen[sa][m] + pen[sb][m]))
        n = len(self.cells)
        r, c, v = np.concatenate(rows), np.concatenate(cols), np.concatenate(vals)
        self.graph = coo_matrix((v, (r, c)), shape=(n, n)).tocsr()

    def node(self, p: np.ndarray) -> int:
        """The usable cell nearest to point ``p`` (-1 if there is none)."""
        if len(self.cells) == 0:
            return -1
        i, j = self.grid.cell(p)
        if self.idx[i, j] >= 0:
            return int(self.idx[i, j])
        d = np.hypot(self.cells[:, 0] - i, self.cells[:, 1] - j)
        k = int(np.argmin(d))
        return k if d[k] * self.grid.h < 0.3 else -1

    def search(self, source: int) -> tuple[np.ndarray, np.ndarray]:
        """Path costs from ``source`` to every node and the predecessor array."""
        dist, pred = dijkstra(self.graph, directed=False, indices=source, return_predecessors=True)
        return dist, pred

    def path(self, pred: np.ndarray, target: int) -> np.ndarray:
        """Map-frame cell centres ``(k, 2)`` from the search's source to ``target``."""
        seq = [target]
        while pred[seq[-1]] >= 0:
            seq.append(int(pred[seq[-1]]))
        cells = self.cells[np.asarray(seq[::-1])]
        return self.grid.centers(cells[:, 0], cells[:, 1])


def simplify(points: np.ndarray, tol: float) -> np.ndarray:
    """Douglas-Peucker simplification of an open polyline ``(k, 2)`` (keeps both ends)."""
    if len(points) < 3:
        return points
    return np.asarray(shapely.simplify(shapely.linestrings(points), tol).coords)
