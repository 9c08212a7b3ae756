"""Parameters of the building generator and of the schematic map (pydantic models).

Every length is in metres, every angle in radians unless a name says otherwise. A field left
``None`` in :class:`BuildingParams` is drawn from the building's seed, so seeds ``0..N`` give a
varied corpus; a field set fixes that choice for every seed.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

BuildingType = Literal["office", "lab", "hospital"]
Layout = Literal["straight", "L", "ring", "atrium"]

BUILDING_TYPES: tuple[BuildingType, ...] = ("office", "lab", "hospital")
LAYOUTS: tuple[Layout, ...] = ("straight", "L", "ring", "atrium")

#: Footprint limits (m): the short side lies in [MIN_SIDE, MAX_SHORT], the long side in
#: [MIN_SIDE, MAX_LONG] (a 10 x 10 m floor up to a 40 x 60 m one, either orientation).
MIN_SIDE = 10.0
MAX_SHORT = 40.0
MAX_LONG = 60.0

#: Clutter density of the office world (sim_publisher/worlds/office.geojson): furniture area
#: 27.0 m^2 over 303.2 m^2 of floor inside the walls (rooms and corridor) = 0.089.
OFFICE_CLUTTER = 0.089


class BuildingParams(BaseModel):
    """What to generate. ``None`` fields are drawn from the seed.

    ``width``/``height`` are the footprint's x/y extents (outer faces of the outer walls).
    ``clutter`` is the furniture area over the floor area inside the walls (rooms, corridors,
    halls); the default is the office world's. ``people`` moving people (circles of radius
    ~0.25 m) walk between rooms. ``tour_length`` is the tour's length (m), capped by what the
    building offers; ``tour_clearance`` the minimum distance (m) the tour keeps from every
    obstacle, furniture included; ``robot_speed`` (m/s) turns arc length into time (for the
    moving people). ``door_width`` bounds every door (m), ``wall_thickness`` every wall (m).
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    building_type: BuildingType | None = None
    layout: Layout | None = None
    width: float | None = Field(default=None, ge=MIN_SIDE, le=MAX_LONG)
    height: float | None = Field(default=None, ge=MIN_SIDE, le=MAX_LONG)
    clutter: float = Field(default=OFFICE_CLUTTER, ge=0.0, le=0.25)
    wall_details: bool = True
    people: int = Field(default=0, ge=0, le=50)
    tour_length: float = Field(default=25.0, gt=1.0, le=500.0)
    tour_clearance: float = Field(default=0.4, ge=0.2, le=0.6)
    robot_speed: float = Field(default=0.5, gt=0.0, le=3.0)
    door_width: tuple[float, float] = (0.8, 1.8)
    wall_thickness: tuple[float, float] = (0.1, 0.3)

    @model_validator(mode="after")
    def _check(self) -> BuildingParams:
        sides = [v for v in (self.width, self.height) if v is not None]
        if len(sides) == 2 and min(sides) > MAX_SHORT:
            raise ValueError(f"the short side must be <= {MAX_SHORT} m, got {min(sides)}")
        lo, hi = self.door_width
        if not 0.7 <= lo <= hi <= 2.5:
            raise ValueError(f"door_width must satisfy 0.7 <= min <= max <= 2.5, got {lo}, {hi}")
        lo, hi = self.wall_thickness
        if not 0.05 <= lo <= hi <= 0.4:
            raise ValueError(
                f"wall_thickness must satisfy 0.05 <= min <= max <= 0.4, got {lo}, {hi}"
            )
        return self


class SchematicParams(BaseModel):
    """How the schematic map departs from the true building.

    ``detail_min_size``: wall details (pilasters, niches, columns attached to walls) standing
    out of or into the wall face by less than this (m) are dropped; larger ones are drawn.
    ``corner_jitter``: every vertex is moved by a distance drawn uniformly in this range (m) in
    a uniform random direction. ``scale_error``: a global scale error (fraction, e.g. 0.01 =
    +1 %) about the building centre; ``None`` draws it uniformly in
    ``[-scale_error_max, scale_error_max]``. ``closed_doors``: the fraction of doors drawn
    closed (a line across the gap at the wall's centre line); 0 leaves every gap open (like
    the office schematic), 1 closes all. ``seed``: the random stream of the jitter, scale and
    door choices; ``None`` uses the building's seed.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    detail_min_size: float = Field(default=0.2, ge=0.0)
    corner_jitter: tuple[float, float] = (0.02, 0.10)
    scale_error: float | None = Field(default=None, ge=-0.1, le=0.1)
    scale_error_max: float = Field(default=0.02, ge=0.0, le=0.1)
    closed_doors: float = Field(default=0.0, ge=0.0, le=1.0)
    seed: int | None = None

    @model_validator(mode="after")
    def _check(self) -> SchematicParams:
        lo, hi = self.corner_jitter
        if not 0.0 <= lo <= hi <= 0.5:
            raise ValueError(f"corner_jitter must satisfy 0 <= min <= max <= 0.5, got {lo}, {hi}")
        return self


@dataclass(frozen=True)
class TypeSpec:
    """Dimensions (m) and room mix of one building type.

    ``corridor``: corridor width between wall centre lines; ``room_depth``: room extent away
    from the corridor; ``room_width``: room extent along it; ``door``: single-door widths;
    ``double_door``: probability of a wide (1.4-1.8 m) door; ``merge``: probability that two
    neighbouring rooms of a row are one; ``rooms``: room kinds and their weights.
    """

    corridor: tuple[float, float]
    room_depth: tuple[float, float]
    room_width: tuple[float, float]
    door: tuple[float, float]
    double_door: float
    merge: float
    rooms: tuple[tuple[str, float], ...]


TYPE_SPECS: dict[str, TypeSpec] = {
    "office": TypeSpec(
        corridor=(1.8, 2.4),
        room_depth=(3.2, 6.5),
        room_width=(2.8, 5.5),
        door=(0.85, 1.1),
        double_door=0.1,
        merge=0.2,
        rooms=(("office", 0.55), ("meeting", 0.2), ("lounge", 0.1), ("storage", 0.15)),
    ),
    "lab": TypeSpec(
        corridor=(2.0, 2.6),
        room_depth=(4.0, 8.0),
        room_width=(3.5, 7.5),
        door=(0.9, 1.3),
        double_door=0.3,
        merge=0.25,
        rooms=(("lab", 0.6), ("office", 0.2), ("storage", 0.2)),
    ),
    "hospital": TypeSpec(
        corridor=(2.4, 3.0),
        room_depth=(3.6, 6.0),
        room_width=(3.0, 4.8),
        door=(1.1, 1.6),
        double_door=0.25,
        merge=0.15,
        rooms=(
            ("patient", 0.5),
            ("treatment", 0.2),
            ("waiting", 0.1),
            ("storage", 0.1),
            ("office", 0.1),
        ),
    ),
}

#: Footprint ranges (short side, long side / short side) each layout draws from when the
#: params leave the size open.
LAYOUT_SIZES: dict[str, tuple[tuple[float, float], tuple[float, float]]] = {
    "straight": ((10.0, 22.0), (1.0, 2.6)),
    "L": ((12.0, 28.0), (1.0, 1.8)),
    "ring": ((16.0, 34.0), (1.0, 1.6)),
    "atrium": ((16.0, 32.0), (1.0, 1.5)),
}

#: Smallest short side (m) at which a layout fits (rooms, corridors and a usable core).
LAYOUT_MIN_SHORT: dict[str, float] = {"straight": 10.0, "L": 11.0, "ring": 14.0, "atrium": 14.0}
