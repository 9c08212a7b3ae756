"""Schematisation: a floor-plan-like map derived from a metric one.

The seed paper (§2.3, §4.1) describes a schematic map as one that keeps the salient boundaries
of free space (room and corridor outlines) and drops what a floor plan does not show
(furniture, clutter, small details), and names Discrete Curve Evolution (DCE, eq. 2) as the
tool that coarsens a shape's granularity while keeping its overall appearance (Barkowsky,
Latecki & Richter 2000). :func:`schematize` applies exactly that, in four steps, all in the
map frame (metres):

1. **Join** (optional, ``merge_gap`` > 0): polylines whose ends face each other across a gap of
   at most ``merge_gap`` and whose end directions agree within ``merge_angle`` degrees are
   joined end to end (a wall broken by an occlusion or a missing return becomes one outline;
   a door wider than ``merge_gap`` stays open). Ends closer than ``snap`` join whatever their
   directions (a corner the map builder left open).
2. **Drop small objects**: every open polyline whose extent (largest distance between two of
   its vertices) is below ``min_extent`` goes (fronts of desks and cabinets, chairs, bins,
   stray returns), and every closed ring below ``min_ring_extent``: a closed outline is an
   object seen from all around (a table, a pillar, a cabinet in a world file); only a
   free-standing wall or a block of rooms is that large.
3. **Simplify corners by DCE** (:mod:`service.core.shapes.dce`): vertices are removed in order of
   least relevance ``d(u, v) + d(v, w) - d(u, w)`` while it is below ``relevance`` metres.
   A right-angle corner with arms ``a`` has relevance ``~0.59 a``; a bump of depth ``d`` on a
   long wall about ``2 d``, so niches, pilasters and boxes along walls shallower than about
   ``relevance / 2`` flatten out. Open polylines keep their end points; closed rings are
   evolved cyclically (restarted at their most relevant vertex, so no vertex is kept only for
   being first). Relevance is small for a long, gently curved wall (a 12 m arc bowed by 0.5 m
   has a mid-vertex relevance of 0.04 m), so DCE alone would replace it by its chord; a guard
   re-inserts, Douglas-Peucker style, the farthest removed vertex of any edge that strays more
   than ``max_deviation`` from the vertices it replaced.
4. **Drop isolated short pieces**: a polyline shorter than ``min_length`` goes unless one of
   its ends lies within ``snap`` of another kept polyline (a door jamb stays, a shelf front
   standing in a room does not).

Deterministic: no randomness; the output order is by each polyline's first vertex (x, then y).
"""

from __future__ import annotations

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from service.adapters.maps.contours import dedupe, is_closed, join_polylines, polyline_length
from service.core import numeric
from service.core.shapes.dce import dce, relevance_array
from service.core.types import MapData
from service.errors import InvalidMessage


class SchematizeParams(BaseModel):
    """Parameters of :func:`schematize` (metres and degrees; defaults in brackets).

    * ``min_extent`` [1.2 m]: open polylines whose extent (largest vertex-to-vertex distance)
      is below this are dropped as objects. Measured on the maps built from the corrected
      fr079 / intel logs: 1.5 m keeps 64 / 65 polylines that put 56 / 67 % of the returns
      within 10 cm, 1.2 m 85 / 84 polylines and 62 / 71 %, 1.0 m 104 / 107 and 66 / 75 %
      (the rest are wall pieces between doors and furniture of that size alike).
    * ``min_ring_extent`` [3.0 m]: closed rings whose extent is below this are dropped.
    * ``relevance`` [0.15 m]: DCE stop threshold (eq. 2 relevance); removes bumps shallower
      than about 7 cm and corners with arms shorter than about 25 cm.
    * ``max_deviation`` [0.15 m]: no vertex removed by DCE lies farther than this from the
      simplified polyline (0 disables the guard).
    * ``min_length`` [0.5 m]: shorter polylines are dropped unless attached (an end within
      ``snap``) to another kept polyline.
    * ``merge_gap`` [0.5 m]: largest gap joined between facing, collinear ends; 0 disables
      joining. Keep it below the narrowest door to keep doors open.
    * ``merge_angle`` [15 deg]: largest difference between the directions of two ends (and
      between an end's direction and the gap) for them to be joined.
    * ``snap`` [0.1 m]: ends closer than this join regardless of direction; also the distance
      at which a short piece counts as attached.
    * ``end_window`` [0.5 m]: arc length over which an end's direction is measured.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    min_extent: float = Field(1.2, ge=0.0, allow_inf_nan=False)
    min_ring_extent: float = Field(3.0, ge=0.0, allow_inf_nan=False)
    relevance: float = Field(0.15, ge=0.0, allow_inf_nan=False)
    max_deviation: float = Field(0.15, ge=0.0, allow_inf_nan=False)
    min_length: float = Field(0.5, ge=0.0, allow_inf_nan=False)
    merge_gap: float = Field(0.5, ge=0.0, allow_inf_nan=False)
    merge_angle: float = Field(15.0, ge=0.0, le=90.0, allow_inf_nan=False)
    snap: float = Field(0.1, ge=0.0, allow_inf_nan=False)
    end_window: float = Field(0.5, gt=0.0, allow_inf_nan=False)


def schematize(map_data: MapData, params: SchematizeParams | None = None) -> MapData:
    """A schematic map (kind ``"schematic"``, same ``map_id``) derived from ``map_data``.

    Steps and parameters: see the module docstring and :class:`SchematizeParams`. Raises
    :class:`InvalidMessage` when nothing survives (e.g. a map of furniture only).
    """
    prm = params if params is not None else SchematizeParams()
    polys = [np.asarray(p, dtype=np.float64) for p in map_data.polylines]
    polys = [dedupe(p) for p in polys]
    polys = [p for p in polys if p.shape[0] >= 2]
    if prm.merge_gap > 0.0 or prm.snap > 0.0:
        polys = join_polylines(
            polys,
            max_gap=prm.merge_gap,
            max_angle=prm.merge_angle,
            snap=prm.snap,
            end_window=prm.end_window,
        )
    polys = [
        p for p in polys if _extent(p) >= (prm.min_ring_extent if is_closed(p) else prm.min_extent)
    ]
    polys = [_evolve(p, prm.relevance, prm.max_deviation) for p in polys]
    polys = _drop_isolated_short(polys, prm)
    if not polys:
        raise InvalidMessage(
            f"schematize: nothing of map {map_data.map_id!r} survives (min_extent "
            f"{prm.min_extent} m, min_length {prm.min_length} m)"
        )
    polys.sort(key=lambda p: (float(p[0, 0]), float(p[0, 1]), float(p[-1, 0]), float(p[-1, 1])))
    return MapData.from_lists(map_data.map_id, "schematic", polys)


# ---------------------------------------------------------------------- helpers
def _extent(p: np.ndarray) -> float:
    """Largest distance between two vertices (metres), via the convex hull's vertices."""
    pts = np.unique(p, axis=0)
    if pts.shape[0] < 2:
        return 0.0
    if pts.shape[0] > 3:
        try:
            from scipy.spatial import ConvexHull

            pts = pts[ConvexHull(pts).vertices]
        except Exception:  # degenerate (collinear) input: use all points
            pass
    d = pts[:, None, :] - pts[None, :, :]
    return float(np.sqrt((d**2).sum(axis=2)).max())


def _guard(p: np.ndarray, keep: np.ndarray, max_dev: float) -> np.ndarray:
    """Kept indices plus, recursively, the farthest vertex of every kept edge whose replaced
    vertices stray more than ``max_dev`` from it."""
    if max_dev <= 0.0:
        return keep
    out: list[int] = [int(keep[0])]
    stack: list[tuple[int, int]] = []
    for a, b in zip(keep[:-1].tolist(), keep[1:].tolist(), strict=True):
        stack.append((a, b))
        while stack:
            i, j = stack.pop()
            if j - i < 2:
                out.append(j)
                continue
            seg = p[j] - p[i]
            ll = numeric.dot(seg, seg)
            q = p[i + 1 : j] - p[i]
            if ll > 0.0:
                t = np.clip(numeric.matvec(q, seg) / ll, 0.0, 1.0)
                d = np.hypot(*(q - t[:, None] * seg).T)
            else:
                d = np.hypot(q[:, 0], q[:, 1])
            k = int(np.argmax(d))
            if d[k] <= max_dev:
                out.append(j)
                continue
            m = i + 1 + k
            stack.append((m, j))  # processed after (i, m): keeps the order increasing
            stack.append((i, m))
    return np.asarray(out, dtype=np.intp)


def _evolve(p: np.ndarray, threshold: float, max_dev: float) -> np.ndarray:
    """DCE to ``threshold`` with the deviation guard; closed rings cyclically (see module
    docstring)."""
    if threshold <= 0.0 or p.shape[0] < 3:
        return p
    if not is_closed(p):
        return p[_guard(p, dce(p, threshold), max_dev)]
    ring = p[:-1]
    # first pass from an arbitrary start, then restart at the most relevant kept vertex so
    # that the start is a genuine corner, and evolve the original ring again from there
    k0 = p[dce(p, threshold)][:-1]
    if k0.shape[0] >= 3:
        closed = np.vstack([k0[-1:], k0, k0[:1]])
        rel = relevance_array(closed)
        start_pt = k0[int(np.argmax(rel))]
        start = int(np.nonzero(np.all(ring == start_pt, axis=1))[0][0])
    else:
        start = 0
    r = np.roll(ring, -start, axis=0)
    closed = np.vstack([r, r[:1]])
    out = closed[_guard(closed, dce(closed, threshold), max_dev)]
    if out.shape[0] < 4:  # collapsed to a there-and-back sliver: one segment
        return out[:2]
    return out


def _drop_isolated_short(polys: list[np.ndarray], prm: SchematizeParams) -> list[np.ndarray]:
    """Drop polylines shorter than ``min_length`` whose ends are not within ``snap`` of
    another polyline that is kept."""
    if not polys or prm.min_length <= 0.0:
        return polys
    lengths = np.array([polyline_length(p) for p in polys])
    long_ = lengths >= prm.min_length
    if long_.all():
        return polys
    keep = long_.copy()
    if prm.snap > 0.0 and long_.any():
        import shapely

        kept_geoms = shapely.linestrings(
            np.concatenate([polys[i] for i in np.nonzero(long_)[0]]),
            indices=np.repeat(
                np.arange(int(long_.sum())), [polys[i].shape[0] for i in np.nonzero(long_)[0]]
            ),
        )
        tree = shapely.STRtree(kept_geoms)
        for i in np.nonzero(~long_)[0]:
            ends = shapely.points(np.vstack([polys[i][0], polys[i][-1]]))
            near = tree.query(ends, predicate="dwithin", distance=prm.snap)
            keep[i] = near.shape[1] > 0
    return [p for p, k in zip(polys, keep, strict=True) if k]
