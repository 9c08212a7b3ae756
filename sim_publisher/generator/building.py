"""``generate_building(seed, params)``: a seeded building, its maps, its tour and its people.

Randomness: only ``numpy.random.default_rng`` seeded from the building seed, one independent
stream per stage (``default_rng([seed, k])``: 0 the type/layout/size draw, 1 the shell, 2 the
furniture, 3 the tour, 4 the people, 6 the schematic map), so e.g. changing the clutter leaves
the walls, doors and schematic map of a seed unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import shapely
from shapely.geometry import Point

from service.adapters.maps.world import Obstacle, World
from service.core.types import MapData
from service.errors import InvalidWorld
from sim_publisher.generator.details import wall_details
from sim_publisher.generator.furniture import Item, furnish
from sim_publisher.generator.layout import Door, Layout, Room, build_layout
from sim_publisher.generator.params import (
    BUILDING_TYPES,
    LAYOUT_MIN_SHORT,
    LAYOUT_SIZES,
    LAYOUTS,
    MAX_LONG,
    MAX_SHORT,
    MIN_SIDE,
    BuildingParams,
    SchematicParams,
)
from sim_publisher.generator.schematic import SchematicMap, schematic_map
from sim_publisher.generator.tours import (
    DOOR_PASS,
    Person,
    RoomPlanners,
    plan_people,
    plan_tour,
)
from sim_publisher.trajectory import Tour

#: Clearance (m) at which the free space must stay one connected area holding every room.
ROBOT_RADIUS = 0.3


@dataclass
class Building:
    """A generated building (map frame, metres, footprint ``[0, width] x [0, height]``).

    ``params`` are the resolved parameters (type, layout and size filled in); ``world`` the
    true world (walls as kind ``wall``, furniture with their kinds); ``tour`` the robot's
    continuous tour (calibrated to the seed paper's turn statistics) and ``visits`` the rooms it
    enters; ``people`` the moving people (empty unless ``params.people``).
    """

    seed: int
    params: BuildingParams
    shell: Layout
    items: list[Item]
    world: World
    tour: Tour
    visits: list[int]
    people: list[Person]

    @property
    def building_type(self) -> str:
        return self.shell.building_type

    @property
    def layout(self) -> str:
        return self.shell.layout

    @property
    def width(self) -> float:
        return self.shell.width

    @property
    def height(self) -> float:
        return self.shell.height

    @property
    def rooms(self) -> list[Room]:
        return self.shell.rooms

    @property
    def doors(self) -> list[Door]:
        return self.shell.doors

    @property
    def name(self) -> str:
        return f"building-{self.seed}"

    def metric_map(self, map_id: str | None = None) -> MapData:
        """The exact metric map: every obstacle ring (furniture included)."""
        return self.world.to_map_data(map_id or self.name)

    def schematic(
        self, params: SchematicParams | None = None, map_id: str | None = None
    ) -> SchematicMap:
        """The schematic map derived with ``params`` (defaults: see SchematicParams)."""
        return schematic_map(
            self.shell, params or SchematicParams(), self.seed, map_id or f"{self.name}-schematic"
        )

    def people_at(self, t: float, avoid_robot: bool = True) -> np.ndarray:
        """Circles ``(k, 3)`` ``[x, y, r]`` (m) of the moving people at time ``t`` (s).

        With ``avoid_robot`` a person closer than ``ROBOT_RADIUS`` to the robot (at its tour
        position at time ``t``) steps aside, straight away from the robot, to that distance.
        """
        if not self.people:
            return np.zeros((0, 3))
        c = np.array([[*p.position(t), p.radius] for p in self.people])
        if avoid_robot:
            s = min(float(t) * self.params.robot_speed, self.tour.length)
            robot = self.tour.poses_at(np.array([s]))[0, :2]
            d = c[:, :2] - robot
            dist = np.hypot(d[:, 0], d[:, 1])
            need = c[:, 2] + ROBOT_RADIUS
            m = dist < need
            if m.any():
                unit = np.where(dist[:, None] > 1e-9, d / np.maximum(dist, 1e-9)[:, None], [1, 0])
                c[m, :2] = robot + unit[m] * need[m, None]
        return c

    def times(self, s: np.ndarray) -> np.ndarray:
        """Time (s) at which the robot passes arc length ``s`` (m) of its tour."""
        return np.asarray(s, dtype=np.float64) / self.params.robot_speed

    @property
    def clutter(self) -> float:
        """Achieved clutter: furniture area over the floor area inside the walls."""
        walls = [o.geometry for o in self.world.obstacles if o.kind == "wall"]
        floor = self.shell.footprint.difference(shapely.union_all(walls)).area
        return float(sum(it.area for it in self.items) / floor)

    def unreachable_rooms(self, radius: float = ROBOT_RADIUS) -> list[int]:
        """Rooms not reachable from the corridors by a disc of ``radius`` m (exact, shapely):
        the free space shrunk by ``radius`` must hold one area with a point of every room."""
        return _unreachable(self.shell, self.world, radius)


def _room_anchor(lay: Layout, room: Room) -> np.ndarray:
    d = lay.doors[room.doors[0]] if room.doors else None
    if d is None:  # reached from a neighbour: use the door that connects it
        d = next(x for x in lay.doors if x.other == room.index)
        return d.center - DOOR_PASS * d.normal
    return d.center + DOOR_PASS * d.normal


def _unreachable(lay: Layout, world: World, radius: float) -> list[int]:
    core = world.free_space.buffer(-radius)
    start = Point(*lay.graph[0][0])
    parts = [g for g in shapely.get_parts(core) if g.distance(start) < 1e-9]
    if not parts:
        return [r.index for r in lay.rooms]
    main = shapely.prepared.prep(parts[0])
    return [r.index for r in lay.rooms if not main.contains(Point(*_room_anchor(lay, r)))]


def _world(walls: object, items: list[Item]) -> World:
    obs = [
        Obstacle(geometry=g, name=f"walls#{k}", kind="wall")
        for k, g in enumerate(shapely.get_parts(walls))
    ]
    for it in items:
        for k, p in enumerate(it.parts):
            name = it.name if len(it.parts) == 1 else f"{it.name}#{k}"
            obs.append(Obstacle(geometry=p, name=name, kind=it.kind))
    return World(obs)


def resolve_params(seed: int, params: BuildingParams | None = None) -> BuildingParams:
    """The parameters building ``seed`` is generated with: ``params`` with the type, layout
    and size filled in from ``default_rng([seed, 0])`` where left open (cheap: no geometry).
    Raises InvalidWorld if the layout cannot fit the size."""
    p = params or BuildingParams()
    rng = np.random.default_rng([seed, 0])
    btype = p.building_type or BUILDING_TYPES[int(rng.integers(len(BUILDING_TYPES)))]
    given = [v for v in (p.width, p.height) if v is not None]
    if p.layout is not None:
        layout = p.layout
    else:
        short = min(given) if given else MAX_SHORT
        ok = [lay for lay in LAYOUTS if LAYOUT_MIN_SHORT[lay] <= short]
        layout = ok[int(rng.integers(len(ok)))]
    (s_lo, s_hi), (a_lo, a_hi) = LAYOUT_SIZES[layout]
    aspect = float(rng.uniform(a_lo, a_hi))
    short = float(rng.uniform(s_lo, s_hi))
    flip = bool(rng.random() < 0.5)
    w, h = p.width, p.height
    if w is None and h is None:
        long = min(MAX_LONG, short * aspect)
        w, h = (long, short) if flip else (short, long)
    elif w is None or h is None:
        g = float(w if w is not None else h)
        other = g * aspect if (g <= MAX_SHORT and flip) or g < s_lo else g / aspect
        other = float(np.clip(other, MIN_SIDE, MAX_LONG if g <= MAX_SHORT else MAX_SHORT))
        w, h = (g, other) if w is not None else (other, g)
    w, h = round(float(w), 2), round(float(h), 2)
    if min(w, h) < LAYOUT_MIN_SHORT[layout]:
        raise InvalidWorld(
            f"generator: a {layout} layout needs a short side >= {LAYOUT_MIN_SHORT[layout]} m, "
            f"got {w} x {h} m"
        )
    return p.model_copy(update={"building_type": btype, "layout": layout, "width": w, "height": h})


def generate_building(seed: int, params: BuildingParams | None = None) -> Building:
    """Generate building ``seed`` (deterministic: same seed and params, same building).

    Raises :class:`InvalidWorld` when the params cannot be met (e.g. a ring layout in a 10 m
    wide footprint).
    """
    seed = int(seed)
    p = resolve_params(seed, params)
    assert p.width is not None and p.height is not None and p.layout and p.building_type
    shell_rng = np.random.default_rng([seed, 1])
    lay = build_layout(
        p.width,
        p.height,
        p.layout,
        p.building_type,
        shell_rng,
        door_bounds=p.door_width,
        wall_bounds=p.wall_thickness,
    )
    if p.wall_details:
        lay.details = wall_details(lay, shell_rng)
    walls = lay.walls()
    items = furnish(lay, walls, p.clutter, np.random.default_rng([seed, 2]))
    world = _world(walls, items)
    bad = _unreachable(lay, world, ROBOT_RADIUS)
    while bad:  # the raster check missed a pocket: take the room's furniture out, newest first
        room_items = [i for i, it in enumerate(items) if it.space in bad]
        if not room_items:
            raise InvalidWorld(f"generator: rooms {bad} of building {seed} are unreachable")
        items.pop(room_items[-1])
        world = _world(walls, items)
        bad = _unreachable(lay, world, ROBOT_RADIUS)
    geoms = [o.geometry for o in world.obstacles]
    tree = shapely.STRtree(geoms)
    planners = RoomPlanners(lay, world.union)
    tour, visits = plan_tour(
        lay,
        world.union,
        tree,
        p.tour_length,
        p.tour_clearance,
        np.random.default_rng([seed, 3]),
        planners,
    )
    people = (
        plan_people(lay, world.union, tree, p.people, np.random.default_rng([seed, 4]), planners)
        if p.people
        else []
    )
    return Building(seed, p, lay, items, world, tour, visits, people)
