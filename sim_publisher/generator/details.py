"""Wall details of a generated building: pilasters, niches and columns attached to walls.

Small features on the inner wall faces (map frame, metres) that the true world has and that a
schematic map drops below a size (:class:`~sim_publisher.generator.params.SchematicParams`):
pilasters (0.2-0.4 m wide, 0.06-0.15 m deep) on room faces, niches (0.6-1.2 m wide,
0.05-0.12 m deep) cut into outer walls, and, in some buildings, square or half-round columns
(0.15-0.3 m deep) attached to the outer walls at a regular 4-7 m spacing. A detail's ``size``
is how far it stands out of (or into) the wall face. Every detail keeps 0.35 m from door gaps
and 0.1 m from other details.
"""

from __future__ import annotations

import math

import numpy as np
import shapely
from shapely.geometry import Polygon, box

from sim_publisher.generator.layout import Layout, Room, WallDetail
from sim_publisher.generator.layout.walls import on_boundary


def _face_box(room: Room, k: int, s: float, along: float, depth: float) -> Polygon:
    """A box of ``along`` x ``depth`` m on the inner face ``k`` of ``room`` centred at ``s``
    along it, standing ``depth`` m into the room (negative depth: into the wall)."""
    r = room.inner
    a = along / 2.0
    if k == 0:
        return box(min(r.x0, r.x0 + depth), s - a, max(r.x0, r.x0 + depth), s + a)
    if k == 1:
        return box(min(r.x1, r.x1 - depth), s - a, max(r.x1, r.x1 - depth), s + a)
    if k == 2:
        return box(s - a, min(r.y0, r.y0 + depth), s + a, max(r.y0, r.y0 + depth))
    return box(s - a, min(r.y1, r.y1 - depth), s + a, max(r.y1, r.y1 - depth))


def _half_round(room: Room, k: int, s: float, rad: float) -> Polygon:
    r = room.inner
    ang = np.linspace(0.0, np.pi, 25)
    u, v = rad * np.cos(ang), rad * np.sin(ang)
    if k == 0:
        pts = np.c_[r.x0 + v, s + u]
    elif k == 1:
        pts = np.c_[r.x1 - v, s + u]
    elif k == 2:
        pts = np.c_[s + u, r.y0 + v]
    else:
        pts = np.c_[s + u, r.y1 - v]
    return Polygon(pts)


def wall_details(lay: Layout, rng: np.random.Generator) -> list[WallDetail]:
    """Pilasters (0.2-0.4 m wide, 0.06-0.15 m deep) on room faces, niches (0.05-0.12 m deep)
    in the outer walls, and, in some buildings, columns (0.15-0.3 m deep, square or
    half-round) attached to the outer walls at a regular spacing."""
    W, H = lay.width, lay.height
    gaps = shapely.union_all([d.gap(0.0).buffer(0.35) for d in lay.doors]) if lay.doors else None
    out: list[WallDetail] = []
    taken: list[Polygon] = []

    def ok(g: Polygon, room: Room) -> bool:
        if gaps is not None and g.intersects(gaps):
            return False
        if not room.inner.poly().buffer(1e-9).contains(g.buffer(-1e-6)):
            return False
        return not any(g.distance(t) < 0.1 for t in taken)

    def along(room: Room, k: int) -> tuple[float, float]:
        r = room.inner
        return (r.y0, r.y1) if k in (0, 1) else (r.x0, r.x1)

    for room in lay.rooms:
        if rng.random() < 0.35:  # pilaster on a random face
            k = int(rng.integers(4))
            lo, hi = along(room, k)
            w, d = rng.uniform(0.2, 0.4), rng.uniform(0.06, 0.15)
            if hi - lo > w + 1.2:
                s = rng.uniform(lo + 0.5 + w / 2, hi - 0.5 - w / 2)
                g = _face_box(room, k, s, w, d)
                if ok(g, room):
                    out.append(WallDetail("pilaster", g, float(d), True))
                    taken.append(g)
        outer = [k for k in range(4) if on_boundary(*room.rect.side(k)[:2], W, H)]
        if outer and rng.random() < 0.2 and lay.t_out >= 0.15:
            k = outer[int(rng.integers(len(outer)))]
            lo, hi = along(room, k)
            w = rng.uniform(0.6, 1.2)
            d = rng.uniform(0.05, min(0.12, lay.t_out - 0.08))
            if hi - lo > w + 1.0:
                s = rng.uniform(lo + 0.5 + w / 2, hi - 0.5 - w / 2)
                g = _face_box(room, k, s, w, -d)
                clear = gaps is None or not g.intersects(gaps)
                if clear and not any(g.distance(t) < 0.1 for t in taken):
                    out.append(WallDetail("niche", g, float(d), False))
                    taken.append(g)
    p_cols = 0.35 if lay.building_type == "office" else 0.6
    if rng.random() < p_cols:
        spacing = rng.uniform(4.0, 7.0)
        rad = rng.uniform(0.15, 0.3)
        square = bool(rng.random() < 0.5)
        wid = rng.uniform(0.3, 0.6)
        for room in lay.rooms:
            for k in range(4):
                if not on_boundary(*room.rect.side(k)[:2], W, H):
                    continue
                lo, hi = along(room, k)
                first = math.ceil((lo + 0.5) / spacing) * spacing
                for s in np.arange(first, hi - 0.5, spacing):
                    if square:
                        g, size = _face_box(room, k, float(s), wid, rad), rad
                    else:
                        g, size = _half_round(room, k, float(s), rad), rad
                    if s - lo > 0.5 + wid and hi - s > 0.5 + wid and ok(g, room):
                        out.append(WallDetail("column", g, float(size), True))
                        taken.append(g)
    return out
