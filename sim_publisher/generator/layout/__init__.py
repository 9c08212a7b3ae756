"""Floor layout: footprint, corridors, rooms, doors and walls of varied thickness.

Everything is in the map frame (metres), x right, y up, the footprint ``[0, W] x [0, H]``
(outer faces of the outer walls). Rooms and corridors are axis-aligned rectangles whose edges
are wall **centre lines** (except on the footprint boundary, where the outer wall lies inside).
Walls are built as the union of a band per room edge (its line's thickness), a post at every
room corner (the intersection of the two bands) and the outer frame, minus the door gaps, so
junctions of walls of different thickness are exact.

A layout is first drawn in a canonical frame (short side along x, corridor system fixed up to a
mirror), then mirrored and transposed to the requested footprint.

The package: :mod:`.types` (:class:`Rect`, :class:`Room`, :class:`Door`, :class:`WallDetail`,
:class:`Layout`, the constants), :mod:`.geometry` (corridor shapes, room tiling),
:mod:`.walls` (wall thicknesses, inner faces, doors, wall core) and :mod:`.build`
(:func:`build_layout`); this module re-exports the public names.
"""

from sim_publisher.generator.layout.build import build_layout
from sim_publisher.generator.layout.geometry import split_length
from sim_publisher.generator.layout.types import (
    DOOR_APPROACH,
    JAMB_MIN,
    MIN_DEPTH,
    Door,
    Layout,
    Rect,
    Room,
    WallDetail,
)

__all__ = [
    "DOOR_APPROACH",
    "JAMB_MIN",
    "MIN_DEPTH",
    "Door",
    "Layout",
    "Rect",
    "Room",
    "WallDetail",
    "build_layout",
    "split_length",
]
