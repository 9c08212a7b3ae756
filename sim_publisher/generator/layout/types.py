"""The layout's data types: :class:`Rect`, :class:`Room`, :class:`Door` (with its gap and
approach area), :class:`WallDetail` and :class:`Layout` (the building shell, whose
:meth:`Layout.walls` cuts the door gaps and adds the details), and the layout constants."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import shapely
from shapely.geometry import Polygon, box

EPS = 1e-6
#: Wall stub (m) kept between a door gap and the corner of the wall it is cut into.
JAMB_MIN = 0.3
#: Smallest room depth (m) any layout leaves for a row of rooms.
MIN_DEPTH = 2.6
#: How far in front of a door (m, from the wall centre line) the approach stays clear.
DOOR_APPROACH = 1.4


@dataclass(frozen=True)
class Rect:
    """Axis-aligned rectangle ``[x0, x1] x [y0, y1]`` (m)."""

    x0: float
    y0: float
    x1: float
    y1: float

    @property
    def w(self) -> float:
        return self.x1 - self.x0

    @property
    def h(self) -> float:
        return self.y1 - self.y0

    @property
    def center(self) -> np.ndarray:
        return np.array([(self.x0 + self.x1) / 2.0, (self.y0 + self.y1) / 2.0])

    def poly(self) -> Polygon:
        return box(self.x0, self.y0, self.x1, self.y1)

    def transposed(self) -> Rect:
        return Rect(self.y0, self.x0, self.y1, self.x1)

    def mirrored(self, W: float, H: float, fx: bool, fy: bool) -> Rect:
        x0, x1 = (W - self.x1, W - self.x0) if fx else (self.x0, self.x1)
        y0, y1 = (H - self.y1, H - self.y0) if fy else (self.y0, self.y1)
        return Rect(x0, y0, x1, y1)

    def side(self, k: int) -> tuple[int, float, float, float]:
        """Side ``k`` (0 left, 1 right, 2 bottom, 3 top) as ``(axis, coord, lo, hi)``: axis 1 is
        a vertical line ``x = coord`` spanning y ``[lo, hi]``, axis 0 a horizontal one."""
        if k == 0:
            return 1, self.x0, self.y0, self.y1
        if k == 1:
            return 1, self.x1, self.y0, self.y1
        if k == 2:
            return 0, self.y0, self.x0, self.x1
        return 0, self.y1, self.x0, self.x1


@dataclass
class Room:
    """A room: its rectangle on wall centre lines, its inner faces, its kind and doors."""

    index: int
    rect: Rect
    kind: str = "office"
    inner: Rect | None = None
    doors: list[int] = field(default_factory=list)

    @property
    def name(self) -> str:
        return f"room{self.index}"


@dataclass(frozen=True)
class Door:
    """A door gap of ``width`` (m) in a wall of ``thickness`` (m) centred at ``center``.

    ``axis`` is the wall's direction (0: the wall runs along x, 1: along y); ``normal`` the
    unit normal pointing into ``room``; ``other`` the room on the far side, or -1 for a
    corridor or hall.
    """

    index: int
    center: np.ndarray
    axis: int
    width: float
    thickness: float
    room: int
    other: int
    normal: np.ndarray

    def gap(self, extra: float = 0.02) -> Polygon:
        """The gap cut through the wall (extends ``extra`` m beyond both faces)."""
        cx, cy = self.center
        a, d = self.width / 2.0, self.thickness / 2.0 + extra
        if self.axis == 0:
            return box(cx - a, cy - d, cx + a, cy + d)
        return box(cx - d, cy - a, cx + d, cy + a)

    def point(self, d: float) -> np.ndarray:
        """The point ``d`` m from the door centre along the normal (into the room if > 0)."""
        return self.center + d * self.normal

    def approach(self) -> Polygon:
        """Area kept free on both sides of the gap (width + 0.5 m wide, DOOR_APPROACH deep)."""
        cx, cy = self.center
        a, d = self.width / 2.0 + 0.25, DOOR_APPROACH
        if self.axis == 0:
            return box(cx - a, cy - d, cx + a, cy + d)
        return box(cx - d, cy - a, cx + d, cy + a)


def make_door(index, center, axis, width, thickness, room, other, normal) -> Door:
    return Door(
        index,
        np.asarray(center, float),
        axis,
        float(width),
        float(thickness),
        room,
        other,
        np.asarray(normal, float),
    )


@dataclass(frozen=True)
class WallDetail:
    """A small wall feature: a pilaster or an attached column (``solid``) or a niche (cut).

    ``size`` is how far it stands out of (or into) the wall face (m).
    """

    kind: str
    geometry: Polygon
    size: float
    solid: bool


@dataclass
class Layout:
    """The building shell: corridors, rooms, doors, walls and wall details (map frame, m)."""

    width: float
    height: float
    layout: str
    building_type: str
    corridors: list[Rect]
    hall: list[bool]
    rooms: list[Room]
    doors: list[Door]
    graph: list[np.ndarray]
    t_out: float
    thickness: dict[tuple[int, float], float]
    core: object  # shapely: walls without details and door gaps
    details: list[WallDetail]

    def walls(self, min_detail: float = 0.0) -> object:
        """Walls (shapely) with the details of ``size >= min_detail`` and every door gap."""
        solids = [d.geometry for d in self.details if d.solid and d.size >= min_detail]
        cuts = [d.geometry for d in self.details if not d.solid and d.size >= min_detail]
        cuts += [d.gap() for d in self.doors]
        g = shapely.union_all([self.core, *solids]) if solids else self.core
        g = g.difference(shapely.union_all(cuts))
        return shapely.normalize(shapely.simplify(g, 1e-9))

    @property
    def footprint(self) -> Polygon:
        return box(0.0, 0.0, self.width, self.height)
