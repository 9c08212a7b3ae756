"""Candidate viewpoints over a map's free space (:func:`candidate_viewpoints`), from each of
which the view index stores a map view."""

from __future__ import annotations

import numpy as np
from shapely import contains_xy
from shapely.geometry import Polygon

from service.core.sensor.raycast import RayCaster
from service.core.types import MapData
from service.errors import LocalizationError

#: Viewpoint grid spacing (m): finer than a room, coarser than a door.
SPACING = 0.6
#: A viewpoint's distance to any polyline (m): where a robot fits.
MIN_CLEARANCE = 0.3
#: Beams of the enclosure test (4 degrees).
ENCLOSURE_BEAMS = 90
#: Closed rings smaller than this (m²) are furniture, not rooms: no viewpoint.
SMALL_RING_AREA = 6.0


def candidate_viewpoints(
    map_data: MapData,
    spacing: float = SPACING,
    *,
    min_clearance: float = MIN_CLEARANCE,
    min_enclosed: float = 0.9,
    max_range: float = 15.0,
    caster: RayCaster | None = None,
) -> np.ndarray:
    """The points ``(v, 2)`` of a ``spacing``-metre grid over the map's free space: farther
    than ``min_clearance`` from every polyline, ``min_enclosed`` of :data:`ENCLOSURE_BEAMS`
    rays hitting a polyline within ``max_range`` (outside a building most escape), and not in
    a closed ring smaller than :data:`SMALL_RING_AREA` (furniture and pillars; rooms are
    larger or drawn open at their doors)."""
    if spacing <= 0:
        raise LocalizationError(f"spacing must be > 0, got {spacing}")
    caster = caster or RayCaster(map_data.segments())
    x0, y0, x1, y1 = map_data.bounds()
    xs = np.arange(x0 + 0.5 * spacing, x1, spacing)
    ys = np.arange(y0 + 0.5 * spacing, y1, spacing)
    if xs.size == 0 or ys.size == 0:
        return np.zeros((0, 2))
    gx, gy = np.meshgrid(xs, ys)
    pts = np.column_stack([gx.ravel(), gy.ravel()])
    clear = _segment_clearance(pts, caster.segments)
    pts = pts[clear > min_clearance]
    rings = [Polygon(p) for p in map_data.polylines if len(p) >= 4 and np.allclose(p[0], p[-1])]
    rings = [r for r in rings if r.is_valid and 0.0 < r.area < SMALL_RING_AREA]
    if rings and len(pts):
        inside = np.zeros(len(pts), dtype=bool)
        for r in rings:
            inside |= contains_xy(r, pts[:, 0], pts[:, 1])
        pts = pts[~inside]
    angles = -np.pi + (np.arange(ENCLOSURE_BEAMS) + 0.5) * (2.0 * np.pi / ENCLOSURE_BEAMS)
    keep = np.zeros(len(pts), dtype=bool)
    for k, p in enumerate(pts):
        r = caster.cast(np.array([p[0], p[1], 0.0]), angles, max_range)
        keep[k] = np.mean(np.isfinite(r)) >= min_enclosed
    return pts[keep]


def _segment_clearance(points: np.ndarray, segments: np.ndarray, chunk: int = 512) -> np.ndarray:
    """Distance (m) from each point to the nearest segment."""
    a = segments[:, 0:2]
    e = segments[:, 2:4] - a
    ee = np.maximum(np.einsum("ij,ij->i", e, e), 1e-18)
    out = np.empty(len(points))
    for s in range(0, len(points), chunk):
        p = points[s : s + chunk]
        dx = p[:, None, 0] - a[None, :, 0]
        dy = p[:, None, 1] - a[None, :, 1]
        u = np.clip((dx * e[None, :, 0] + dy * e[None, :, 1]) / ee[None, :], 0.0, 1.0)
        out[s : s + chunk] = np.sqrt(
            np.min((dx - u * e[None, :, 0]) ** 2 + (dy - u * e[None, :, 1]) ** 2, axis=1)
        )
    return out
