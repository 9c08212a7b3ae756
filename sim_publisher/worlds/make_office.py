"""Generate ``office.geojson`` and ``office_schematic.geojson`` (run once; outputs committed).

    python -m service.adapters.maps.worlds.make_office

The office recreates the kind of test environment of the paper's Fig. 6a: a 14 x 23 m floor
(map frame, metres, x 0..14, y 0..23) with seven rooms off a north-south corridor, thin walls
with 0.95 m door gaps, furniture, non-linear obstacles and a round pillar near the west wall of
the top-left room. The schematic map (Fig. 6b) keeps only the room and corridor outlines along
the inner wall faces, drops pilasters and niches, and displaces every vertex by 2-8 cm with a
seeded generator. The committed files are the runtime source of truth.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import shapely
from shapely.geometry import Polygon, box, mapping

HERE = Path(__file__).resolve().parent
WIDTH, HEIGHT = 14.0, 23.0
T_OUT = 0.15  # outer wall thickness (m)
T_IN = 0.12  # interior wall thickness (m)
DOOR = 0.95  # door gap width (m)
WEST_X, EAST_X = 5.6, 7.6  # corridor wall centre lines
SCHEMATIC_SEED = 20070101
ROUND = 4  # decimals written (0.1 mm)


def _hwall(y: float, x0: float, x1: float, doors: tuple[float, ...] = ()) -> list[Polygon]:
    """Horizontal interior wall centred on ``y`` from ``x0`` to ``x1`` with door gaps."""
    return _split(x0, x1, doors, lambda a, b: box(a, y - T_IN / 2, b, y + T_IN / 2))


def _vwall(x: float, y0: float, y1: float, doors: tuple[float, ...] = ()) -> list[Polygon]:
    """Vertical interior wall centred on ``x`` from ``y0`` to ``y1`` with door gaps."""
    return _split(y0, y1, doors, lambda a, b: box(x - T_IN / 2, a, x + T_IN / 2, b))


def _split(lo: float, hi: float, doors: tuple[float, ...], make) -> list[Polygon]:
    out, a = [], lo
    for c in sorted(doors):
        out.append(make(a, c - DOOR / 2))
        a = c + DOOR / 2
    out.append(make(a, hi))
    return out


def _walls(details: bool):
    parts = [
        box(0, 0, WIDTH, T_OUT),
        box(0, HEIGHT - T_OUT, WIDTH, HEIGHT),
        box(0, 0, T_OUT, HEIGHT),
        box(WIDTH - T_OUT, 0, WIDTH, HEIGHT),
    ]
    parts += _vwall(WEST_X, 0, HEIGHT, doors=(3.0, 7.6, 10.6, 14.5, 19.8))
    parts += _vwall(EAST_X, 0, HEIGHT, doors=(4.0, 11.5, 18.5))
    parts += _hwall(6.0, 0, WEST_X)
    parts += _hwall(12.0, 0, WEST_X)
    parts += _hwall(17.0, 0, WEST_X)
    parts += _hwall(8.0, EAST_X, WIDTH)
    parts += _hwall(15.0, EAST_X, WIDTH, doors=(11.0,))
    if details:
        wf, ef = WEST_X + T_IN / 2, EAST_X - T_IN / 2  # corridor faces
        for y in (6.0, 12.0, 17.0):
            parts.append(box(wf, y - 0.15, wf + 0.12, y + 0.15))
        for y in (8.0, 15.0):
            parts.append(box(ef - 0.12, y - 0.15, ef, y + 0.15))
        parts.append(box(T_OUT, 18.35, T_OUT + 0.12, 18.65))  # pilaster, top-left room
        parts.append(box(12.0, T_OUT, 12.3, T_OUT + 0.12))  # pilaster, bottom-right room
    walls = shapely.union_all(parts)
    if details:
        niches = [
            box(WIDTH - T_OUT, 2.3, WIDTH - T_OUT + 0.1, 3.3),  # bottom-right room, east
            box(1.8, HEIGHT - T_OUT, 2.9, HEIGHT - T_OUT + 0.1),  # top-left room, north
            box(T_OUT - 0.1, 12.4, T_OUT, 13.4),  # west room 3, west
        ]
        walls = walls.difference(shapely.union_all(niches))
    walls = shapely.normalize(shapely.simplify(walls, 1e-9))
    assert walls.geom_type in ("Polygon", "MultiPolygon"), walls.geom_type
    return walls


def _circle(cx: float, cy: float, r: float, n: int = 64) -> Polygon:
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return Polygon(np.c_[cx + r * np.cos(a), cy + r * np.sin(a)])


def _blob(cx: float, cy: float) -> Polygon:
    """A smooth kidney-like closed curve (mean radius ~0.6 m), 72 vertices."""
    a = np.linspace(0, 2 * np.pi, 72, endpoint=False)
    r = 0.6 + 0.18 * np.cos(2 * a + 0.4) + 0.08 * np.sin(3 * a) + 0.05 * np.cos(5 * a + 1.0)
    return Polygon(np.c_[cx + 1.15 * r * np.cos(a), cy + 0.85 * r * np.sin(a)])


def _irregular(cx: float, cy: float) -> Polygon:
    """A non-convex polygonal object (e.g. a crate pile), 9 vertices."""
    ang = np.deg2rad([0, 35, 80, 120, 160, 200, 245, 290, 325])
    rad = np.array([0.75, 0.45, 0.7, 0.5, 0.8, 0.4, 0.65, 0.55, 0.35])
    return Polygon(np.c_[cx + rad * np.cos(ang), cy + rad * np.sin(ang)])


def furniture() -> list[tuple[str, str, Polygon]]:
    """(id, kind, polygon) of every non-wall obstacle."""
    L = shapely.union_all([box(0.2, 11.3, 2.4, 11.89), box(0.2, 10.2, 0.75, 11.89)])
    items = [
        # bottom-left room (x 0.15..5.54, y 0.15..5.94)
        ("desk-L1a", "furniture", box(0.6, 0.6, 2.2, 1.4)),
        ("desk-L1b", "furniture", box(3.0, 0.6, 4.6, 1.4)),
        ("shelf-L1", "furniture", box(0.2, 2.5, 0.55, 4.5)),
        ("cabinet-L1", "furniture", box(3.8, 5.4, 5.45, 5.89)),
        # west room 2 (y 6.06..11.94): blob, L-shaped counter, cabinet
        ("blob-L2", "complex", _blob(2.9, 8.8)),
        ("counter-L2", "furniture", L),
        ("cabinet-L2", "furniture", box(4.0, 6.11, 5.45, 6.55)),
        # west room 3 (y 12.06..16.94)
        ("desk-L3a", "furniture", box(0.6, 12.5, 2.2, 13.3)),
        ("desk-L3b", "furniture", box(0.6, 15.8, 2.2, 16.6)),
        ("shelf-L3", "furniture", box(0.2, 13.8, 0.55, 15.3)),
        ("cabinet-L3", "furniture", box(4.2, 16.3, 5.45, 16.89)),
        # top-left room (y 17.06..22.85): round pillar 0.45 m off the west wall
        ("pillar-L4", "circle", _circle(T_OUT + 0.45 + 0.4, 21.6, 0.4, 64)),
        ("desk-L4", "furniture", box(0.6, 17.15, 2.2, 17.85)),
        ("shelf-L4", "furniture", box(3.3, 22.4, 5.2, 22.8)),
        # bottom-right room (x 7.66..13.85, y 0.15..7.94)
        ("crates-R1", "complex", _irregular(10.6, 3.4)),
        ("desk-R1a", "furniture", box(8.0, 0.4, 9.8, 1.1)),
        ("desk-R1b", "furniture", box(11.0, 7.25, 12.6, 7.89)),
        ("cabinet-R1", "furniture", box(13.3, 5.0, 13.8, 7.0)),
        # east room 2 (y 8.06..14.94)
        ("table-R2", "furniture", box(9.5, 10.5, 11.5, 12.0)),
        ("shelf-R2", "furniture", box(13.3, 8.5, 13.8, 11.5)),
        ("desk-R2", "furniture", box(8.0, 14.2, 9.6, 14.89)),
        # top-right room (y 15.06..22.85)
        ("round-table-R3", "circle", _circle(11.0, 19.0, 0.5, 64)),
        ("desk-R3", "furniture", box(12.0, 21.9, 13.8, 22.8)),
        ("cabinet-R3", "furniture", box(8.0, 22.3, 9.4, 22.8)),
        # corridor
        ("cooler-C", "furniture", box(5.71, 1.5, 6.05, 1.85)),
    ]
    return items


def _rounded(geom) -> dict:
    m = mapping(shapely.set_precision(geom, 10.0**-ROUND))
    return json.loads(json.dumps(m))


def world_geojson() -> dict:
    feats = [
        {
            "type": "Feature",
            "properties": {"id": "walls", "kind": "wall"},
            "geometry": _rounded(_walls(details=True)),
        }
    ]
    for fid, kind, poly in furniture():
        feats.append(
            {
                "type": "Feature",
                "properties": {"id": fid, "kind": kind},
                "geometry": _rounded(shapely.normalize(poly)),
            }
        )
    return {"type": "FeatureCollection", "name": "office", "features": feats}


def _drop_collinear(pts: np.ndarray) -> np.ndarray:
    keep = [0]
    for i in range(1, len(pts) - 1):
        a, b, c = pts[keep[-1]], pts[i], pts[i + 1]
        cross = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
        if abs(cross) > 1e-9:
            keep.append(i)
    keep.append(len(pts) - 1)
    return pts[keep]


def schematic_geojson() -> dict:
    """Free-space outline of the detail-free walls, split at door jambs, vertices jittered."""
    walls = _walls(details=False)
    polys = list(getattr(walls, "geoms", [walls]))
    rings = []
    for poly in polys:
        # The building outline (outer face of the outer walls) is not a free-space boundary.
        if poly.exterior.bounds != (0.0, 0.0, WIDTH, HEIGHT):
            rings.append(poly.exterior)
        rings.extend(poly.interiors)
    rng = np.random.default_rng(SCHEMATIC_SEED)
    feats = []
    for ring in rings:
        pts = np.asarray(ring.coords)[:-1]
        n = len(pts)
        edge_len = np.hypot(*(np.roll(pts, -1, axis=0) - pts).T)
        short = np.flatnonzero(edge_len < 0.2)  # door jambs (wall thickness)
        assert len(short) > 0
        for k, s in enumerate(short):
            e = short[(k + 1) % len(short)]
            idx = [(s + 1 + j) % n for j in range((e - s) % n or n)] + [e]
            piece = _drop_collinear(pts[idx])
            feats.append(piece)
    out = []
    for k, piece in enumerate(feats):
        ang = rng.uniform(0, 2 * np.pi, len(piece))
        mag = rng.uniform(0.02, 0.08, len(piece))
        jittered = piece + np.c_[mag * np.cos(ang), mag * np.sin(ang)]
        out.append(
            {
                "type": "Feature",
                "properties": {"id": f"outline-{k}"},
                "geometry": {
                    "type": "LineString",
                    "coordinates": np.round(jittered, ROUND).tolist(),
                },
            }
        )
    return {"type": "FeatureCollection", "name": "office-schematic", "features": out}


def main() -> None:
    (HERE / "office.geojson").write_text(json.dumps(world_geojson(), indent=1) + "\n")
    (HERE / "office_schematic.geojson").write_text(json.dumps(schematic_geojson(), indent=1) + "\n")
    print("wrote", HERE / "office.geojson", HERE / "office_schematic.geojson")


if __name__ == "__main__":
    main()
