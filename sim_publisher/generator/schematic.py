"""The schematic map of a generated building (the floor-plan counterpart of the true world).

Derived like the office's (``sim_publisher/worlds/make_office.py``): the outlines of the free
space of rooms, corridors and halls drawn along the **inner wall faces**, as polylines of kind
``schematic``; the building's outer outline is not drawn. Departures from the true building,
all set by :class:`~sim_publisher.generator.params.SchematicParams`:

* furniture (and every free-standing obstacle) is dropped: only walls are outlined;
* wall details (pilasters, niches, attached columns) standing out of / into the face by less
  than ``detail_min_size`` are dropped (the outline runs straight past them);
* door gaps are left open (the outline stops at both jambs; the jambs are not drawn) or, for a
  ``closed_doors`` share of the doors, drawn closed by a line across the gap along the wall's
  centre line;
* collinear vertices are merged, then every vertex is moved by a distance drawn uniformly in
  ``corner_jitter`` in a uniform random direction (a closed outline moves its first and last
  vertex together);
* finally everything is scaled by ``1 + scale_error`` about the building centre.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import shapely
from shapely.geometry import box

from service.core.types import MapData
from sim_publisher.generator.layout import Layout
from sim_publisher.generator.params import SchematicParams


@dataclass(frozen=True)
class SchematicMap:
    """A schematic map and how it was made.

    ``clean``: the outlines (and closed-door lines) before jitter and scaling, exactly on the
    inner wall faces (map frame, m); ``map_data`` holds them jittered and scaled, in the same
    order. ``scale`` is ``1 + scale error``, applied about ``center``. ``closed_doors`` lists
    the indices of doors drawn closed; ``details_kept`` / ``details_dropped`` count wall
    details.
    """

    map_data: MapData
    clean: tuple[np.ndarray, ...]
    scale: float
    center: np.ndarray
    closed_doors: tuple[int, ...]
    details_kept: int
    details_dropped: int

    def unscaled(self) -> tuple[np.ndarray, ...]:
        """The map's polylines with the scale error undone (jitter only)."""
        return tuple(self.center + (p - self.center) / self.scale for p in self.map_data.polylines)


def _drop_collinear(pts: np.ndarray, closed: bool) -> np.ndarray:
    if closed:
        ring = pts[:-1]
        n = len(ring)
        keep = []
        for i in range(n):
            a, b, c = ring[i - 1], ring[i], ring[(i + 1) % n]
            cross = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
            if abs(cross) > 1e-9:
                keep.append(i)
        r = ring[keep]
        return np.vstack([r, r[:1]])
    keep = [0]
    for i in range(1, len(pts) - 1):
        a, b, c = pts[keep[-1]], pts[i], pts[i + 1]
        cross = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
        if abs(cross) > 1e-9:
            keep.append(i)
    keep.append(len(pts) - 1)
    return pts[keep]


def _jamb_cut(lay: Layout) -> object:
    """The door gaps, 0.1 mm wider than the gap so the jamb faces fall strictly inside."""
    cuts = []
    for d in lay.doors:
        cx, cy = d.center
        a, t = d.width / 2.0 + 1e-4, d.thickness / 2.0 + 0.05
        cuts.append(
            box(cx - a, cy - t, cx + a, cy + t)
            if d.axis == 0
            else box(cx - t, cy - a, cx + t, cy + a)
        )
    return shapely.union_all(cuts) if cuts else None


def schematic_map(
    lay: Layout, params: SchematicParams, seed: int, map_id: str = "schematic"
) -> SchematicMap:
    """Derive the schematic map of a building shell (see the module docstring)."""
    rng = np.random.default_rng([int(params.seed if params.seed is not None else seed), 6])
    closed_draw = rng.random(len(lay.doors))
    closed = tuple(int(d.index) for d in lay.doors if closed_draw[d.index] < params.closed_doors)
    walls = lay.walls(min_detail=params.detail_min_size)
    free = lay.footprint.difference(walls)
    lines = shapely.get_parts(shapely.boundary(free))
    cut = _jamb_cut(lay)
    if cut is not None:
        lines = shapely.get_parts(shapely.difference(shapely.union_all(lines), cut))
    merged = shapely.line_merge(shapely.union_all(lines)) if len(lines) else None
    clean: list[np.ndarray] = []
    for g in shapely.get_parts(merged) if merged is not None else []:
        pts = np.asarray(g.coords)[:, :2]
        if len(pts) < 2:
            continue
        closed_ring = bool(np.allclose(pts[0], pts[-1]))
        pts = _drop_collinear(pts, closed_ring)
        if len(pts) >= 2:
            clean.append(pts)
    for k in closed:
        d = lay.doors[k]
        along = np.array([1.0, 0.0]) if d.axis == 0 else np.array([0.0, 1.0])
        clean.append(np.array([d.center - along * d.width / 2, d.center + along * d.width / 2]))
    # order deterministically (shapely's part order is, but make it explicit)
    clean.sort(key=lambda p: (round(float(p[0, 0]), 6), round(float(p[0, 1]), 6), len(p)))
    lo, hi = params.corner_jitter
    out = []
    for pts in clean:
        closed_ring = len(pts) > 2 and bool(np.allclose(pts[0], pts[-1]))
        n = len(pts) - 1 if closed_ring else len(pts)
        ang = rng.uniform(0.0, 2.0 * np.pi, n)
        mag = rng.uniform(lo, hi, n)
        disp = np.c_[mag * np.cos(ang), mag * np.sin(ang)]
        if closed_ring:
            disp = np.vstack([disp, disp[:1]])
        out.append(pts + disp)
    s = (
        params.scale_error
        if params.scale_error is not None
        else float(rng.uniform(-params.scale_error_max, params.scale_error_max))
    )
    center = np.array([lay.width / 2.0, lay.height / 2.0])
    scale = 1.0 + s
    out = [center + scale * (p - center) for p in out]
    kept = sum(1 for d in lay.details if d.size >= params.detail_min_size)
    return SchematicMap(
        map_data=MapData.from_lists(map_id, "schematic", out),
        clean=tuple(clean),
        scale=scale,
        center=center,
        closed_doors=closed,
        details_kept=kept,
        details_dropped=len(lay.details) - kept,
    )
