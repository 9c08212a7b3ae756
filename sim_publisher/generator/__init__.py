"""Seeded generator of buildings, their metric and schematic maps, tours and moving people.

    from sim_publisher.generator import generate_building, BuildingParams, SchematicParams
    b = generate_building(7)                      # type, layout and size drawn from seed 7
    b.world, b.metric_map(), b.schematic().map_data, b.tour.poses(0.011)

Modules: :mod:`.params` (pydantic parameters), :mod:`.layout` (corridors, rooms, doors,
walls), :mod:`.details` (pilasters, niches, attached columns), :mod:`.furniture` (obstacle
catalogue and placement), :mod:`.schematic` (schematic map), :mod:`.tours` (robot tour and
people's paths), :mod:`.grid` (raster helpers), :mod:`.building` (``generate_building``).
See docs/simulator.md, "Generated buildings".
"""

from sim_publisher.generator.building import Building, generate_building, resolve_params
from sim_publisher.generator.params import (
    BUILDING_TYPES,
    LAYOUTS,
    OFFICE_CLUTTER,
    BuildingParams,
    SchematicParams,
)
from sim_publisher.generator.schematic import SchematicMap

__all__ = [
    "BUILDING_TYPES",
    "LAYOUTS",
    "OFFICE_CLUTTER",
    "Building",
    "BuildingParams",
    "SchematicMap",
    "SchematicParams",
    "generate_building",
    "resolve_params",
]
