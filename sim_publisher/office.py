"""The office test environment (see docs/simulator.md) and its two maps.

``office_world()`` is the TRUE world (walls, furniture, non-linear obstacles) that scans are
simulated against. ``office_metric_map()`` is its exact metric map; ``office_schematic_map()``
is the floor-plan-like schematic map (room outlines only). All in map-frame metres. Both files
live in ``sim_publisher/worlds/`` and are read by :mod:`service.adapters.maps` (world and map
files).
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

from service.adapters.maps.files import load_map_file
from service.adapters.maps.world import World, load_world
from service.core.types import MapData

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


def office_schematic_map(map_id: str = "office-schematic") -> MapData:
    """Schematic office map: room/corridor outlines along inner wall faces, door gaps kept,
    no furniture, no pilasters/niches, vertices displaced by 2-8 cm."""
    return load_map_file(OFFICE_SCHEMATIC_PATH, map_id=map_id, kind="schematic")
