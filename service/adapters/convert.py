"""Wire messages <-> core types: the edge's one conversion module.

The wire (:mod:`schemas`) does not know the core and the core does not know the wire; the
node, the clients and the simulator convert here. Imports :mod:`schemas` and
:mod:`service.core.types` only (no zenoh).
"""

from __future__ import annotations

from schemas.messages import Map
from service.core.types import MapData


def map_data_of(msg: Map) -> MapData:
    """The core's view of a validated wire map: same id, kind and read-only ``(k, 2)``
    polylines (metres, map frame)."""
    return MapData(map_id=msg.map_id, kind=msg.kind, polylines=msg.polylines)


def map_message_of(map_data: MapData, name: str | None = None) -> Map:
    """The wire :class:`~schemas.messages.Map` of a core map (validated like any message)."""
    return Map(
        map_id=map_data.map_id,
        kind=map_data.kind,
        polylines=[p.tolist() for p in map_data.polylines],
        name=name,
    )
