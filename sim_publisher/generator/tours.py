"""Routes through a generated building: the robot's tour and the moving people's paths.

A route is a control polyline (map frame, metres) that the tour machinery of
:mod:`sim_publisher.trajectory` smooths (Chaikin corner cut) and samples:

* along corridors and halls it follows the corridor graph (centre lines, the atrium's
  gallery loop), which furniture keeps clear of (``CORRIDOR_RESERVE`` / ``HALL_RESERVE``);
* through a door it runs straight along the door's normal from 0.9 m before the wall centre
  line to 0.9 m after it (four collinear control points, so the smoothed curve is straight
  through the gap);
* inside a room it follows shortest paths on a 0.1 m raster over cells with >= 0.5 m
  clearance (paths pulled to the middle of the free space), from the door to a far point,
  on to a second far point and back to the door.

Control polylines are subdivided to <= 0.4 m edges before smoothing so corner cuts stay within
~0.1 m of them, and the smoothed tour is checked exactly (shapely) for its clearance; a room
whose visit breaks it is left out and the tour is planned again.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import numpy as np
import shapely
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from service.errors import InvalidWorld
from sim_publisher.generator.grid import Grid, GridPlanner, simplify
from sim_publisher.generator.layout import Door, Layout
from sim_publisher.trajectory import Tour

#: Distance (m) of the door pass points from the wall centre line.
DOOR_PASS = 0.9
#: Longest control-polygon edge (m) before smoothing.
MAX_EDGE = 0.4
_RASTER = 0.1
_PLAN_MIN = 0.5  # raster clearance (m) a room path keeps
_PLAN_PREF = 0.8  # raster clearance (m) below which a room path pays extra


# --------------------------------------------------------------------------- corridor graph
class CorridorGraph:
    """Shortest routes along the corridor graph's polylines (map frame, m)."""

    def __init__(self, lines: list[np.ndarray]) -> None:
        pts: list[tuple[float, float]] = []
        key: dict[tuple[float, float], int] = {}
        edges = []
        for line in lines:
            ids = []
            for p in line:
                k = (round(float(p[0]), 6), round(float(p[1]), 6))
                if k not in key:
                    key[k] = len(pts)
                    pts.append(k)
                ids.append(key[k])
            edges.extend((a, b) for a, b in itertools.pairwise(ids) if a != b)
        self.nodes = np.asarray(pts, dtype=np.float64)
        self.edges = np.asarray(edges, dtype=np.int64)
        a, b = self.nodes[self.edges[:, 0]], self.nodes[self.edges[:, 1]]
        w = np.hypot(*(b - a).T)
        n = len(self.nodes)
        g = coo_matrix((w, (self.edges[:, 0], self.edges[:, 1])), shape=(n, n)).tocsr()
        self.dist, self.pred = dijkstra(g, directed=False, return_predecessors=True)

    def project(self, p: np.ndarray) -> tuple[int, np.ndarray]:
        """Nearest edge to ``p`` and the foot point on it."""
        a, b = self.nodes[self.edges[:, 0]], self.nodes[self.edges[:, 1]]
        e = b - a
        t = np.clip(np.einsum("ij,ij->i", p - a, e) / np.einsum("ij,ij->i", e, e), 0.0, 1.0)
        foot = a + t[:, None] * e
        k = int(np.argmin(np.hypot(*(foot - p).T)))
        return k, foot[k]

    def _node_path(self, i: int, j: int) -> list[int]:
        seq = [j]
        while seq[-1] != i:
            seq.append(int(self.pred[i, seq[-1]]))
        return seq[::-1]

    def route(self, p: np.ndarray, q: np.ndarray) -> np.ndarray:
        """Polyline ``(k, 2)`` from ``p`` to its foot on the graph, along the graph, to the
        foot of ``q`` and to ``q``."""
        ep, fp = self.project(p)
        eq, fq = self.project(q)
        if ep == eq:
            return np.array([p, fp, fq, q])
        best, best_path = np.inf, None
        for i in self.edges[ep]:
            for j in self.edges[eq]:
                d = (
                    np.hypot(*(self.nodes[i] - fp))
                    + self.dist[i, j]
                    + np.hypot(*(self.nodes[j] - fq))
                )
                if d < best:
                    best, best_path = d, self._node_path(int(i), int(j))
        mid = self.nodes[np.asarray(best_path)]
        return np.vstack([p, fp, mid, fq, q])


# --------------------------------------------------------------------------- rooms
@dataclass
class RoomPlanner:
    """Raster planner over one room (free space minus walls and furniture)."""

    planner: GridPlanner
    clear: np.ndarray


def room_planner(lay: Layout, room: int, obstacles: object) -> RoomPlanner:
    """Plan over room ``room``'s rectangle; ``obstacles``: shapely union of walls+furniture."""
    rect = lay.rooms[room].rect
    grid = Grid.over((rect.x0, rect.y0, rect.x1, rect.y1), _RASTER)
    grid.free = grid.mask(rect.poly().difference(obstacles))
    clear = grid.clearance()
    return RoomPlanner(GridPlanner(grid, clear, _PLAN_MIN, _PLAN_PREF), clear)


def _door_normal_into(door: Door, room: int) -> np.ndarray:
    return door.normal if door.room == room else -door.normal


def door_pass(door: Door, room: int, leaving: bool) -> np.ndarray:
    """Four collinear control points through ``door``: leaving (or entering) ``room``."""
    n = _door_normal_into(door, room)
    d = np.array([DOOR_PASS, DOOR_PASS / 2, -DOOR_PASS / 2, -DOOR_PASS])
    if not leaving:
        d = d[::-1]
    return door.center + d[:, None] * n


@dataclass(frozen=True)
class Loop:
    """A visit inside a room: door -> far point ``to_far``, far point -> second far point
    ``across``, second far point -> door ``back`` (polylines, map frame, m)."""

    to_far: np.ndarray
    across: np.ndarray
    back: np.ndarray

    def path(self, mode: str) -> np.ndarray:
        """``through`` (door -> far -> second far -> door), ``start`` (far -> second far ->
        door) or ``end`` (door -> far -> second far)."""
        parts = {
            "through": [self.to_far, self.across, self.back],
            "start": [self.across, self.back],
            "end": [self.to_far, self.across],
        }[mode]
        return np.vstack([parts[0], *(p[1:] for p in parts[1:])])


def room_loop(rp: RoomPlanner, p_in: np.ndarray, rng) -> Loop | None:
    """A visit of a room from ``p_in`` (the inner door pass point): a far point among the
    cells with >= 0.6 m clearance (>= 70 % of the farthest path cost), then a second one far
    from both. None if the room offers no path of >= 2 m at the planning clearance."""
    pl = rp.planner
    src = pl.node(p_in)
    if src < 0:
        return None
    dist, pred = pl.search(src)
    cells = pl.cells
    good = np.isfinite(dist) & (rp.clear[cells[:, 0], cells[:, 1]] >= 0.6)
    if not good.any() or dist[good].max() < 2.0:
        return None
    cand = np.flatnonzero(good & (dist >= 0.7 * dist[good].max()))
    w1 = int(rng.choice(cand))
    dist2, pred2 = pl.search(w1)
    score = np.minimum(dist, dist2)
    cand = np.flatnonzero(good & (score >= 0.7 * score[good].max()))
    w2 = int(rng.choice(cand))
    to_w1 = pl.path(pred, w1)
    back = pl.path(pred, w2)[::-1]
    to_w1[0] = p_in
    back[-1] = p_in
    return Loop(simplify(to_w1, 0.05), simplify(pl.path(pred2, w2), 0.05), simplify(back, 0.05))


def subdivide(points: np.ndarray, max_edge: float = MAX_EDGE) -> np.ndarray:
    """Insert points so that no edge of the polyline is longer than ``max_edge`` m; drops
    repeated points."""
    p = np.asarray(points, dtype=np.float64)
    keep = np.r_[True, np.hypot(*np.diff(p, axis=0).T) > 1e-9]
    p = p[keep]
    out = [p[:1]]
    for a, b in itertools.pairwise(p):
        n = max(1, int(np.ceil(np.hypot(*(b - a)) / max_edge)))
        t = np.arange(1, n + 1)[:, None] / n
        out.append(a + t * (b - a))
    return np.vstack(out)


# --------------------------------------------------------------------------- the tour
@dataclass
class RoomPlanners:
    lay: Layout
    obstacles: object
    cache: dict[int, RoomPlanner | None] = field(default_factory=dict)

    def get(self, room: int) -> RoomPlanner:
        if room not in self.cache:
            self.cache[room] = room_planner(self.lay, room, self.obstacles)
        return self.cache[room]  # type: ignore[return-value]


def tour_doors(lay: Layout, min_width: float) -> dict[int, Door]:
    """Each room's widest corridor/hall door, if wide enough for the tour."""
    out: dict[int, Door] = {}
    for d in lay.doors:
        if d.other == -1 and d.width >= min_width:
            cur = out.get(d.room)
            if cur is None or d.width > cur.width:
                out[d.room] = d
    return out


def min_clearance(tree: shapely.STRtree, pts: np.ndarray) -> np.ndarray:
    """Distance (m) from each point ``(n, 2)`` to the nearest geometry of ``tree``."""
    idx, d = tree.query_nearest(shapely.points(pts), return_distance=True, all_matches=False)
    out = np.full(len(pts), np.inf)
    np.minimum.at(out, idx[0], d)
    return out


def plan_tour(
    lay: Layout,
    obstacles: object,
    tree: shapely.STRtree,
    length: float,
    clearance: float,
    rng: np.random.Generator,
    planners: RoomPlanners | None = None,
) -> tuple[Tour, list[int]]:
    """The tour (calibrated to the paper's turn statistics, truncated to ``length`` m) and the
    rooms it visits in order. Raises InvalidWorld if no room can be visited."""
    planners = planners or RoomPlanners(lay, obstacles)
    doors = tour_doors(lay, 2.0 * clearance + 0.06)
    graph = CorridorGraph(lay.graph)
    excluded: set[int] = set()
    for _ in range(8):
        # smoothing shortens the control polygon: plan ~8 % + 1 m beyond the goal
        control, visits = _route(lay, graph, planners, doors, excluded, 1.08 * length + 1.0, rng)
        if control is None:
            break
        tour = Tour.from_control_points(subdivide(control))
        if tour.length > length:
            tour = tour.truncated(length)
        probe = tour.xy[:: max(1, int(0.01 / (tour.s[1] - tour.s[0])))]
        c = min_clearance(tree, probe)
        if c.min() >= clearance:
            return tour.calibrated(), _entered(lay, tour, visits)
        bad = probe[int(np.argmin(c))]
        culprit = _room_at(lay, bad)
        excluded.add(culprit if culprit >= 0 and culprit in visits else visits[-1])
    raise InvalidWorld(
        f"generator: no tour keeps {clearance} m clearance in this {lay.layout} building"
    )


def _entered(lay: Layout, tour: Tour, visits: list[int]) -> list[int]:
    """The planned visits the (truncated) tour really makes: >= 0.5 m inside the room."""
    xy = np.asarray(tour.xy)
    ds = float(tour.s[1] - tour.s[0]) if len(tour.s) > 1 else 0.0
    out = []
    for k in visits:
        r = lay.rooms[k].inner
        inside = (xy[:, 0] > r.x0) & (xy[:, 0] < r.x1) & (xy[:, 1] > r.y0) & (xy[:, 1] < r.y1)
        if inside.sum() * ds >= 0.5:
            out.append(k)
    return out


def _room_at(lay: Layout, p: np.ndarray) -> int:
    for room in lay.rooms:
        r = room.rect
        if r.x0 <= p[0] <= r.x1 and r.y0 <= p[1] <= r.y1:
            return room.index
    return -1


def _route(lay, graph, planners, doors, excluded, length, rng):
    """Control polyline of a tour: start inside a room, leave it, then visit rooms (nearest
    ones along the corridors first, with some randomness) until ``length`` m; the last room
    is entered and not left. Returns ``(control, visited rooms)``."""
    order = [int(r) for r in rng.permutation(sorted(r for r in doors if r not in excluded))]
    pieces: list[np.ndarray] = []
    visits: list[int] = []
    total = 0.0
    cur: Door | None = None
    while order:
        if cur is None:
            room = order.pop(0)
        else:  # one of the three nearest remaining rooms along the corridors
            here = cur.point(-DOOR_PASS) if cur.room == visits[-1] else cur.point(DOOR_PASS)
            d = [_plen(graph.route(here, _outside(doors[r], r))) for r in order]
            near = np.argsort(d)[:3]
            room = order.pop(int(near[int(rng.integers(len(near)))]))
        door = doors[room]
        p_in = door_inside_point(door, room)
        rp = planners.get(room)
        loop = room_loop(rp, p_in, rng)
        if loop is None:
            continue
        if cur is None:
            path = loop.path("start")
            pieces.append(path)
            total += _plen(path)
        else:
            corridor = graph.route(_outside(cur, visits[-1]), _outside(door, room))
            total += _plen(corridor) + 2 * DOOR_PASS
            end = loop.path("end")
            last = total + _plen(end) >= length or not order
            path = end if last else loop.path("through")
            pieces.extend([corridor, door_pass(door, room, leaving=False), path])
            total += _plen(path)
            if last:
                visits.append(room)
                break
        visits.append(room)
        pieces.append(door_pass(door, room, leaving=True))
        total += 2 * DOOR_PASS
        cur = door
    if not visits:
        return None, []
    return np.vstack(pieces), visits


def door_inside_point(door: Door, room: int) -> np.ndarray:
    return door.center + DOOR_PASS * _door_normal_into(door, room)


def _outside(door: Door, room: int) -> np.ndarray:
    return door.center - DOOR_PASS * _door_normal_into(door, room)


def _plen(p: np.ndarray) -> float:
    return float(np.hypot(*np.diff(p, axis=0).T).sum()) if len(p) > 1 else 0.0


# --------------------------------------------------------------------------- people
@dataclass(frozen=True)
class Person:
    """A person (circle of ``radius`` m) walking back and forth along ``path`` (a dense
    ``(m, 2)`` polyline with arc lengths ``s``) at ``speed`` m/s, ``phase`` m ahead at t = 0."""

    path: np.ndarray
    s: np.ndarray
    radius: float
    speed: float
    phase: float

    def position(self, t: float | np.ndarray) -> np.ndarray:
        """Position(s) (m) at time(s) ``t`` (s): ``(2,)`` or ``(n, 2)``."""
        L = float(self.s[-1])
        u = np.mod(self.phase + self.speed * np.asarray(t, dtype=np.float64), 2.0 * L)
        a = np.where(u <= L, u, 2.0 * L - u)
        return np.stack(
            [np.interp(a, self.s, self.path[:, 0]), np.interp(a, self.s, self.path[:, 1])], axis=-1
        )


def plan_people(
    lay: Layout,
    obstacles: object,
    tree: shapely.STRtree,
    count: int,
    rng: np.random.Generator,
    planners: RoomPlanners | None = None,
) -> list[Person]:
    """``count`` people, each walking between two rooms through their doors and the
    corridors, keeping 0.05 m from every static obstacle."""
    planners = planners or RoomPlanners(lay, obstacles)
    doors = tour_doors(lay, 0.8)
    rooms = sorted(doors)
    graph = CorridorGraph(lay.graph)
    people: list[Person] = []
    if len(rooms) < 2:
        return people
    tries = 0
    while len(people) < count and tries < 6 * count:
        tries += 1
        a, b = (int(v) for v in rng.choice(rooms, 2, replace=False))
        da, db = doors[a], doors[b]
        loop_a = room_loop(planners.get(a), door_inside_point(da, a), rng)
        loop_b = room_loop(planners.get(b), door_inside_point(db, b), rng)
        if loop_a is None or loop_b is None:
            continue
        la, lb = loop_a.path("start"), loop_b.path("end")
        corridor = graph.route(_outside(da, a), _outside(db, b))
        ctrl = np.vstack([la, door_pass(da, a, True), corridor, door_pass(db, b, False), lb])
        t = Tour.from_control_points(subdivide(ctrl), 5)
        path = np.asarray(t.xy[::10])
        radius = float(rng.uniform(0.22, 0.28))
        if min_clearance(tree, path).min() < radius + 0.05:
            continue
        s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(path, axis=0).T))])
        speed = float(rng.uniform(0.6, 1.2))
        people.append(Person(path, s, radius, speed, float(rng.uniform(0.0, 2.0 * s[-1]))))
    return people
