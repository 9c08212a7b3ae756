"""The office test environment (see docs/world.md) and its two maps.

``office_world()`` is the TRUE world (walls, furniture, non-linear obstacles) that scans are
simulated against. ``office_metric_map()`` is its exact metric map; ``office_schematic_map()``
is the floor-plan-like schematic map (room outlines only). All in map-frame metres.
"""

from __future__ import annotations

import json
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

from service.core.types import MapData
from service.errors import InvalidWorld
from service.maps.world import World, load_world

WORLDS_DIR = Path(__file__).resolve().parent / "worlds"
OFFICE_WORLD_PATH = WORLDS_DIR / "office.geojson"
OFFICE_SCHEMATIC_PATH = WORLDS_DIR / "office_schematic.geojson"


@lru_cache(maxsize=1)
def office_world() -> World:
    """The true office world (cached; treat as read-only)."""
    return load_world(OFFICE_WORLD_PATH)


def office_metric_map(map_id: str = "office") -> MapData:
    """Exact metric map of the office: every obstacle ring as a closed polyline."""
    return office_world().to_map_data(map_id)


def load_polylines_geojson(path: str | Path) -> list[np.ndarray]:
    """Read a GeoJSON FeatureCollection of LineStrings/MultiLineStrings as ``(k, 2)`` arrays.

    Raises :class:`InvalidWorld` naming the feature on any problem.
    """
    p = Path(path)
    try:
        doc = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InvalidWorld(f"{p}: unreadable ({exc})") from exc
    if not isinstance(doc, dict) or not isinstance(doc.get("features"), list):
        raise InvalidWorld(f"{p}: not a GeoJSON FeatureCollection")
    out: list[np.ndarray] = []
    for i, feat in enumerate(doc["features"]):
        geom = feat.get("geometry") if isinstance(feat, dict) else None
        gtype = geom.get("type") if isinstance(geom, dict) else None
        if gtype == "LineString":
            lines = [geom.get("coordinates")]
        elif gtype == "MultiLineString":
            lines = geom.get("coordinates")
        else:
            raise InvalidWorld(f"{p}: feature {i}: geometry type {gtype!r} is not a LineString")
        for line in lines if isinstance(lines, list) else [None]:
            try:
                a = np.asarray(line, dtype=np.float64)
            except (TypeError, ValueError) as exc:
                raise InvalidWorld(f"{p}: feature {i}: malformed coordinates") from exc
            if a.ndim != 2 or a.shape[1] != 2 or a.shape[0] < 2:
                raise InvalidWorld(f"{p}: feature {i}: expected >= 2 points of 2 coordinates")
            if not np.all(np.isfinite(a)):
                raise InvalidWorld(f"{p}: feature {i}: non-finite coordinate")
            out.append(a)
    if not out:
        raise InvalidWorld(f"{p}: no polylines")
    return out


def office_schematic_map(map_id: str = "office-schematic") -> MapData:
    """Schematic office map: room/corridor outlines along inner wall faces, door gaps kept,
    no furniture, no pilasters/niches, vertices displaced by 2-8 cm."""
    return MapData.from_lists(map_id, "schematic", load_polylines_geojson(OFFICE_SCHEMATIC_PATH))


def map_message(map_data: MapData, name: str | None = None) -> dict[str, Any]:
    """Wire dict of a map (``{"map_id", "kind", "polylines", "name"}``, plain floats)."""
    return {
        "map_id": map_data.map_id,
        "kind": map_data.kind,
        "polylines": [[[float(x), float(y)] for x, y in p] for p in map_data.polylines],
        "name": name if name is not None else map_data.map_id,
    }
