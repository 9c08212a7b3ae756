"""A bucket grid over a map's segments, to find the segments near a set of points without
measuring every point against every segment.

Global search refines each of its candidate poses against "the segments near the scan points"
(:func:`service.core.reloc.global_search._refine`). Measured on the real logs' metric maps
(1500-2700 segments, 180-360 points per scan) the brute-force selection took ~6 ms per pose and half
of a search's time; floor plans (50-500 segments) barely noticed it. The grid returns exactly the
same segments in the same order as the brute-force reference
:func:`nearby_segments_brute`: the grid only decides which segments are
measured, the test itself is the reference's arithmetic on those.
"""

from __future__ import annotations

import numpy as np

from service.core import kernels
from service.core.kernels import search as search_kernels


def _near_mask(segments: np.ndarray, points: np.ndarray, radius: float) -> np.ndarray:
    """For each segment, whether it lies within ``radius`` of any of ``points`` (the exact
    point-to-segment distance, squared, compared with ``radius²``); compiled
    (:func:`service.core.kernels.search.near_mask`) where numba is installed."""
    if kernels.HAVE_NUMBA:
        return search_kernels.near_mask(
            np.ascontiguousarray(segments, dtype=np.float64),
            np.ascontiguousarray(points, dtype=np.float64),
            float(radius),
        )
    return _near_mask_reference(segments, points, radius)


def _near_mask_reference(segments: np.ndarray, points: np.ndarray, radius: float) -> np.ndarray:
    """:func:`_near_mask` in numpy (every point against every segment)."""
    a = segments[:, 0:2]
    e = segments[:, 2:4] - a
    ee = np.maximum(np.einsum("ij,ij->i", e, e), 1e-18)
    dx = points[:, None, 0] - a[None, :, 0]
    dy = points[:, None, 1] - a[None, :, 1]
    u = np.clip((dx * e[None, :, 0] + dy * e[None, :, 1]) / ee[None, :], 0.0, 1.0)
    d2 = (dx - u * e[None, :, 0]) ** 2 + (dy - u * e[None, :, 1]) ** 2
    return np.min(d2, axis=0) <= radius * radius


def nearby_segments_brute(segments: np.ndarray, points: np.ndarray, radius: float) -> np.ndarray:
    """The segments ``(s, 4)`` within ``radius`` metres of any of ``points`` ``(n, 2)``, in
    their original order; all of them if none is (the reference: every point against every
    segment)."""
    near = _near_mask(segments, points, radius)
    return segments[near] if np.any(near) else segments


class SegmentGrid:
    """Segments bucketed by the ``cell``-metre grid cells their bounding boxes cover.

    A segment within ``radius`` of a point has its nearest point to it inside a cell at most
    ``ceil(radius / cell)`` cells from the point's cell, and that cell is covered by the
    segment's bounding box, so the segments registered in those cells are a superset of the
    answer; :meth:`nearby` measures only them.
    """

    def __init__(self, segments: np.ndarray, cell: float = 1.0) -> None:
        seg = np.ascontiguousarray(segments, dtype=np.float64).reshape(-1, 4)
        self.segments = seg
        self.cell = float(cell)
        if len(seg) == 0:
            self.origin = np.zeros(2)
            self.shape = (0, 0)
            self.start = np.zeros(1, dtype=np.int64)
            self.ids = np.zeros(0, dtype=np.int64)
            return
        lo = np.minimum(seg[:, 0:2], seg[:, 2:4])
        hi = np.maximum(seg[:, 0:2], seg[:, 2:4])
        self.origin = lo.min(axis=0)
        i0 = np.floor((lo - self.origin) / self.cell).astype(np.int64)
        i1 = np.floor((hi - self.origin) / self.cell).astype(np.int64)
        nx, ny = int(i1[:, 0].max()) + 1, int(i1[:, 1].max()) + 1
        self.shape = (ny, nx)
        cells: list[np.ndarray] = []
        owners: list[np.ndarray] = []
        for s in range(len(seg)):
            xs = np.arange(i0[s, 0], i1[s, 0] + 1)
            ys = np.arange(i0[s, 1], i1[s, 1] + 1)
            c = (ys[:, None] * nx + xs[None, :]).ravel()
            cells.append(c)
            owners.append(np.full(c.size, s, dtype=np.int64))
        cell_of = np.concatenate(cells)
        owner = np.concatenate(owners)
        order = np.lexsort((owner, cell_of))
        self.ids = owner[order]
        counts = np.bincount(cell_of, minlength=nx * ny)
        self.start = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)

    def candidates(self, points: np.ndarray, radius: float) -> np.ndarray:
        """Sorted indices of the segments registered within ``ceil(radius / cell)`` cells of
        any of ``points`` (a superset of those within ``radius``)."""
        ny, nx = self.shape
        if nx == 0 or len(points) == 0:
            return np.zeros(0, dtype=np.int64)
        k = int(np.ceil(radius / self.cell))
        ij = np.floor((np.asarray(points, dtype=np.float64) - self.origin) / self.cell)
        ij = ij[np.all(np.isfinite(ij), axis=1)]
        ij = ij[(ij[:, 0] >= -k) & (ij[:, 0] < nx + k) & (ij[:, 1] >= -k) & (ij[:, 1] < ny + k)]
        if len(ij) == 0:
            return np.zeros(0, dtype=np.int64)
        base = np.unique(ij.astype(np.int64), axis=0)
        off = np.arange(-k, k + 1)
        gx = (base[:, 0:1, None] + off[None, None, :]).repeat(len(off), axis=1)
        gy = (base[:, 1:2, None] + off[None, :, None]).repeat(len(off), axis=2)
        gx, gy = gx.ravel(), gy.ravel()
        ok = (gx >= 0) & (gx < nx) & (gy >= 0) & (gy < ny)
        cells = np.unique(gy[ok] * nx + gx[ok])
        lo, hi = self.start[cells], self.start[cells + 1]
        if not np.any(hi > lo):
            return np.zeros(0, dtype=np.int64)
        total = hi - lo
        idx = np.repeat(lo - np.concatenate([[0], np.cumsum(total)[:-1]]), total)
        idx += np.arange(int(total.sum()))
        return np.unique(self.ids[idx])

    def nearby(self, points: np.ndarray, radius: float) -> np.ndarray:
        """Same as :func:`nearby_segments_brute` on this grid's segments (same rows, same
        order, all segments when none is near), measuring only the grid's candidates."""
        cand = self.candidates(points, radius)
        if cand.size == 0:
            return self.segments
        near = _near_mask(self.segments[cand], np.asarray(points, dtype=np.float64), radius)
        return self.segments[cand[near]] if np.any(near) else self.segments
