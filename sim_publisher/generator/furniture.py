"""Furniture: the catalogue of obstacle shapes and their seeded placement at a clutter density.

Kinds (the obstacle ``kind`` written into the world): ``furniture`` (rectangular: desks,
shelves, cupboards, benches, beds, tables), ``circle`` (round tables, round columns near walls,
free-standing columns), ``irregular`` (non-convex polygons: crate piles, equipment), ``blob``
(non-linear smooth outlines: blobs, plants) and ``complex`` (an L-shaped couch or counter, a
table with its chairs). Sizes are metres; every shape is built in a local frame whose x axis
runs along the wall it may stand against and whose y axis points into the room (y >= 0).

Placement keeps every item inside its room (clear of walls and wall details), out of the door
approaches, 0.1 m from other items, and keeps the room navigable: after each item the room's
free cells with >= 0.3 m clearance must form one connected area holding every door approach
(checked on a 0.1 m raster; the building is checked again exactly with shapely afterwards).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import shapely
from shapely import affinity
from shapely.geometry import LineString, Polygon, box
from shapely.prepared import prep

from service.core import numeric
from sim_publisher.generator.grid import Grid, main_component_share
from sim_publisher.generator.layout import Layout, Rect
from sim_publisher.generator.layout.walls import line_key

#: Clearance (m) the free space of a room keeps connected after every placement.
NAV_RADIUS = 0.3
#: Distance (m) between two items.
ITEM_GAP = 0.1
#: Distance (m) corridor / hall items keep from the route lines of the corridor graph.
CORRIDOR_RESERVE = 0.65
HALL_RESERVE = 0.9
_RASTER = 0.1


@dataclass(frozen=True)
class Item:
    """A placed piece of furniture: one or more polygons (a table with chairs has several)."""

    name: str
    item: str
    kind: str
    parts: tuple[Polygon, ...]
    space: int

    @property
    def area(self) -> float:
        return float(sum(p.area for p in self.parts))


# --------------------------------------------------------------------------- shapes
def _circle(cx: float, cy: float, r: float, n: int = 48) -> Polygon:
    a = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    return Polygon(np.c_[cx + r * np.cos(a), cy + r * np.sin(a)])


def _rect(l: float, d: float) -> Polygon:  # noqa: E741
    return box(-l / 2.0, 0.0, l / 2.0, d)


def _star(radius: np.ndarray, n_ang: np.ndarray, sx: float = 1.0, sy: float = 1.0) -> Polygon:
    pts = np.c_[sx * radius * np.cos(n_ang), sy * radius * np.sin(n_ang)]
    pts[:, 1] -= pts[:, 1].min()
    return Polygon(pts)


def _irregular(rng) -> list[Polygon]:
    n = int(rng.integers(7, 12))
    ang = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False) + rng.uniform(-0.2, 0.2, n)
    big = rng.uniform(0.4, 0.8)
    return [_star(big * rng.uniform(0.45, 1.0, n), ang)]


def _blob(rng) -> list[Polygon]:
    a = np.linspace(0.0, 2.0 * np.pi, 72, endpoint=False)
    r = (
        1.0
        + rng.uniform(0.1, 0.25) * np.cos(2 * a + rng.uniform(0, 6.3))
        + rng.uniform(0.0, 0.1) * np.sin(3 * a + rng.uniform(0, 6.3))
        + rng.uniform(0.0, 0.06) * np.cos(5 * a + rng.uniform(0, 6.3))
    )
    return [_star(r, a, rng.uniform(0.5, 0.8), rng.uniform(0.35, 0.5))]


def _plant(rng) -> list[Polygon]:
    a = np.linspace(0.0, 2.0 * np.pi, 64, endpoint=False)
    r0 = rng.uniform(0.2, 0.4)
    k = int(rng.integers(5, 9))
    return [_star(r0 * (1.0 + rng.uniform(0.1, 0.2) * np.sin(k * a + rng.uniform(0, 6.3))), a)]


def _l_shape(rng, depth: tuple[float, float], l1: tuple[float, float], l2) -> list[Polygon]:
    d = rng.uniform(*depth)
    a, b = rng.uniform(*l1), rng.uniform(*l2)
    g = shapely.union_all([box(0.0, 0.0, a, d), box(0.0, 0.0, d, b)])
    return [affinity.translate(g, -a / 2.0, 0.0)]


def _table_chairs(rng) -> list[Polygon]:
    c = 0.42  # chair side (m)
    gap = rng.uniform(0.08, 0.15)
    parts: list[Polygon] = []
    if rng.random() < 0.5:
        r = rng.uniform(0.45, 0.7)
        off = r + gap + c / 2.0 + 0.45  # centre offset so y >= 0 after the shift below
        parts.append(_circle(0.0, off, r, 48))
        n = int(rng.integers(4, 7))
        for k in range(n):
            t = 2.0 * np.pi * k / n + rng.uniform(-0.1, 0.1)
            cx, cy = (r + gap + c / 2.0) * np.cos(t), off + (r + gap + c / 2.0) * np.sin(t)
            ch = affinity.rotate(box(-c / 2, -c / 2, c / 2, c / 2), t, use_radians=True)
            parts.append(affinity.translate(ch, cx, cy))
    else:
        ln, wd = rng.uniform(1.2, 2.0), rng.uniform(0.8, 1.0)
        y0 = c + gap
        parts.append(box(-ln / 2, y0, ln / 2, y0 + wd))
        n = max(1, int(ln // 0.65))
        xs = (np.arange(n) - (n - 1) / 2.0) * (ln / n)
        for x in xs:
            parts.append(box(x - c / 2, 0.0, x + c / 2, c))
            parts.append(box(x - c / 2, y0 + wd + gap, x + c / 2, y0 + wd + gap + c))
        if rng.random() < 0.5:
            yc = y0 + wd / 2
            parts.append(box(ln / 2 + gap, yc - c / 2, ln / 2 + gap + c, yc + c / 2))
    miny = min(p.bounds[1] for p in parts)
    return [affinity.translate(p, 0.0, -miny) for p in parts]


Shape = Callable[[np.random.Generator], list[Polygon]]

#: item -> (kind, shape factory, placement strategies and their weights)
CATALOGUE: dict[str, tuple[str, Shape, dict[str, float]]] = {
    "desk": (
        "furniture",
        lambda g: [_rect(g.uniform(1.2, 1.8), g.uniform(0.6, 0.8))],
        {"wall": 0.6, "free": 0.4},
    ),
    "shelf": (
        "furniture",
        lambda g: [_rect(g.uniform(0.8, 2.0), g.uniform(0.3, 0.45))],
        {"wall": 1.0},
    ),
    "cupboard": (
        "furniture",
        lambda g: [_rect(g.uniform(0.6, 1.4), g.uniform(0.45, 0.6))],
        {"wall": 0.7, "corner": 0.3},
    ),
    "cabinet": (
        "furniture",
        lambda g: [_rect(g.uniform(0.3, 0.6), g.uniform(0.3, 0.35))],
        {"wall": 0.8, "corner": 0.2},
    ),
    "table": (
        "furniture",
        lambda g: [_rect(g.uniform(1.4, 2.4), g.uniform(0.8, 1.2))],
        {"free": 1.0},
    ),
    "bench": (
        "furniture",
        lambda g: [_rect(g.uniform(1.8, 3.5), g.uniform(0.7, 0.9))],
        {"wall": 0.7, "free": 0.3},
    ),
    "seat": (
        "furniture",
        lambda g: [_rect(g.uniform(1.2, 2.0), g.uniform(0.4, 0.5))],
        {"free": 1.0},
    ),
    "bed": (
        "furniture",
        lambda g: [_rect(g.uniform(0.9, 1.0), g.uniform(1.95, 2.1))],
        {"wall": 1.0},
    ),
    "round_table": (
        "circle",
        lambda g: [_circle(0.0, (r := g.uniform(0.35, 0.6)), r)],
        {"free": 1.0},
    ),
    "column": (
        "circle",
        lambda g: [_circle(0.0, (r := g.uniform(0.15, 0.35)), r, 64)],
        {"near_wall": 1.0},
    ),
    "pillar": (
        "circle",
        lambda g: [_circle(0.0, (r := g.uniform(0.2, 0.35)), r, 64)],
        {"free": 1.0},
    ),
    "crates": ("irregular", _irregular, {"free": 0.5, "wall": 0.5}),
    "equipment": ("irregular", _irregular, {"wall": 0.6, "free": 0.4}),
    "blob": ("blob", _blob, {"free": 1.0}),
    "plant": ("blob", _plant, {"corner": 0.4, "wall": 0.3, "free": 0.3}),
    "couch": (
        "complex",
        lambda g: _l_shape(g, (0.75, 0.9), (1.6, 2.4), (1.1, 1.7)),
        {"corner": 0.6, "wall": 0.4},
    ),
    "counter": (
        "complex",
        lambda g: _l_shape(g, (0.5, 0.65), (1.4, 2.4), (0.9, 1.8)),
        {"corner": 1.0},
    ),
    "table_chairs": ("complex", _table_chairs, {"free": 1.0}),
}

#: Room kind -> items and their weights.
RECIPES: dict[str, dict[str, float]] = {
    "office": {
        "desk": 4,
        "shelf": 2,
        "cupboard": 2,
        "plant": 1,
        "round_table": 0.5,
        "crates": 0.3,
        "counter": 0.3,
    },
    "meeting": {"table_chairs": 3, "cupboard": 1, "plant": 1, "shelf": 0.5, "round_table": 0.5},
    "lounge": {"couch": 2, "round_table": 1.5, "plant": 1.5, "blob": 1},
    "storage": {"shelf": 4, "crates": 2, "cupboard": 2, "equipment": 1},
    "lab": {
        "bench": 4,
        "cupboard": 2,
        "equipment": 2,
        "shelf": 1,
        "blob": 0.3,
        "counter": 0.5,
        "column": 0.3,
    },
    "patient": {"bed": 3, "cupboard": 1.5, "round_table": 0.7, "plant": 0.7, "cabinet": 1},
    "treatment": {"bench": 2, "bed": 1, "cupboard": 2, "equipment": 1.5},
    "waiting": {"table_chairs": 1, "couch": 1.5, "plant": 2, "round_table": 1},
    "corridor": {"cabinet": 2, "plant": 1},
    "hall": {"pillar": 1, "plant": 2, "blob": 1, "seat": 1, "round_table": 0.5, "counter": 0.5},
}

#: One of each kind the seed paper names, placed first when the clutter is not zero.
MUST_HAVE = ("desk", "round_table", "crates", "blob", "plant", "couch", "table_chairs", "column")


# --------------------------------------------------------------------------- spaces
@dataclass
class Space:
    """A room, a corridor piece or a hall that furniture is placed into."""

    index: int
    kind: str
    rect: Rect
    inner: Rect
    allowed: object
    keepout: object
    reserve: object | None
    reserve_dist: float
    seeds: list[np.ndarray]
    grid: Grid | None = None
    items: list[Item] = field(default_factory=list)
    occupied: np.ndarray | None = None
    walls: object = None


def _frame(inner: Rect, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float]:
    """Origin on face ``k`` (its low end), unit vector along the face, inward normal, and the
    face's extent ``(lo, hi)`` along that vector."""
    if k == 0:
        return (
            np.array([inner.x0, 0.0]),
            np.array([0.0, 1.0]),
            np.array([1.0, 0.0]),
            inner.y0,
            inner.y1,
        )
    if k == 1:
        return (
            np.array([inner.x1, 0.0]),
            np.array([0.0, 1.0]),
            np.array([-1.0, 0.0]),
            inner.y0,
            inner.y1,
        )
    if k == 2:
        return (
            np.array([0.0, inner.y0]),
            np.array([1.0, 0.0]),
            np.array([0.0, 1.0]),
            inner.x0,
            inner.x1,
        )
    return (
        np.array([0.0, inner.y1]),
        np.array([1.0, 0.0]),
        np.array([0.0, -1.0]),
        inner.x0,
        inner.x1,
    )


def _place(parts: list[Polygon], o: np.ndarray, t: np.ndarray, n: np.ndarray) -> list[Polygon]:
    """Local item frame (x along ``t``, y along ``n``) to the map frame, origin at ``o``."""
    m = np.array([t, n])
    return list(
        shapely.transform(np.asarray(parts, dtype=object), lambda c: o + numeric.matmul(c, m))
    )


def _candidate(space: Space, item: str, rng) -> list[Polygon] | None:
    _, shape, strategies = CATALOGUE[item]
    names = list(strategies)
    w = np.asarray([strategies[s] for s in names])
    strat = names[int(rng.choice(len(names), p=w / w.sum()))]
    parts = shape(rng)
    bb = shapely.bounds(np.asarray(parts, dtype=object))
    bx0, by0 = bb[:, 0].min(), bb[:, 1].min()
    bx1, by1 = bb[:, 2].max(), bb[:, 3].max()
    inner = space.inner
    if strat in ("wall", "near_wall"):
        k = int(rng.integers(4))
        base, t, n, lo, hi = _frame(inner, k)
        gap = rng.uniform(0.3, 0.5) if strat == "near_wall" else rng.uniform(0.02, 0.06)
        half = (bx1 - bx0) / 2.0
        if hi - lo < 2 * half + 0.1:
            return None
        s = rng.uniform(lo + half + 0.05, hi - half - 0.05)
        o = base + s * t + gap * n - (bx0 + half) * t
        placed = _place(parts, o, t, n)
        # a column near a wall: that wall must be its nearest (the gap is the seed's 0.3-0.5 m)
        if strat == "near_wall" and abs(shapely.distance(space.walls, placed[0]) - gap) > 1e-6:
            return None
        return placed
    if strat == "corner":
        kx, ky = int(rng.integers(2)), 2 + int(rng.integers(2))
        x = inner.x0 if kx == 0 else inner.x1
        y = inner.y0 if ky == 2 else inner.y1
        sx = 1.0 if kx == 0 else -1.0
        sy = 1.0 if ky == 2 else -1.0
        g = rng.uniform(0.02, 0.05)
        t, n = np.array([sx, 0.0]), np.array([0.0, sy])
        if rng.random() < 0.5:
            t, n = np.array([0.0, sy]), np.array([sx, 0.0])
        o = np.array([x, y]) + g * (t + n) - bx0 * t
        return _place(parts, o, t, n)
    # free: random centre and heading
    cx, cy = (bx0 + bx1) / 2.0, (by0 + by1) / 2.0
    rad = float(np.hypot(bx1 - bx0, by1 - by0)) / 2.0
    m = rad + 0.3
    if inner.w < 2 * m or inner.h < 2 * m:
        m = min(inner.w, inner.h) / 2.0 - 0.01
    c = np.array([rng.uniform(inner.x0 + m, inner.x1 - m), rng.uniform(inner.y0 + m, inner.y1 - m)])
    th = rng.choice([0.0, np.pi / 2]) if rng.random() < 0.7 else rng.uniform(0.0, np.pi)
    t = np.array([np.cos(th), np.sin(th)])
    n = np.array([-t[1], t[0]])
    return _place(parts, c - cx * t - cy * n, t, n)


def _fits(space: Space, parts: list[Polygon], others: list[Polygon]) -> bool:
    for p in parts:
        if not p.is_valid or not space.allowed.contains(p):
            return False
        if space.keepout is not None and space.keepout.intersects(p):
            return False
    if others:
        arr = np.asarray(others, dtype=object)
        for p in parts:
            if np.any(shapely.distance(arr, p) < ITEM_GAP):
                return False
    if space.reserve is not None:
        for p in parts:
            if p.distance(space.reserve) < space.reserve_dist:
                return False
    return True


def _navigable(space: Space, parts: list[Polygon]) -> np.ndarray | None:
    """The occupancy after adding ``parts`` if the room stays navigable, else None."""
    if space.grid is None:
        return space.occupied
    g = space.grid
    occ = space.occupied | g.mask(shapely.union_all(parts))
    clear = g.clearance(g.free & ~occ)
    seeds = [g.cell(p) for p in space.seeds]
    if main_component_share(clear >= NAV_RADIUS, seeds) < 0.97:
        return None
    return occ


def try_place(space: Space, item: str, rng, name: str, tries: int = 8) -> Item | None:
    """Place one ``item`` in ``space`` (up to ``tries`` candidates); None if none fits."""
    others = [p for it in space.items for p in it.parts]
    for _ in range(tries):
        parts = _candidate(space, item, rng)
        if parts is None or not _fits(space, parts, others):
            continue
        occ = _navigable(space, parts)
        if occ is None:
            continue
        space.occupied = occ
        it = Item(name, item, CATALOGUE[item][0], tuple(parts), space.index)
        space.items.append(it)
        return it
    return None


def make_spaces(lay: Layout, walls: object) -> list[Space]:
    """Rooms (index >= 0), corridor pieces and halls (index < 0) ready for placement."""
    free = lay.footprint.difference(walls)
    approaches = [d.approach() for d in lay.doors]
    ap_all = shapely.union_all(approaches) if approaches else None
    graph = shapely.union_all([LineString(g) for g in lay.graph])
    spaces: list[Space] = []
    for room in lay.rooms:
        allowed = free.intersection(room.rect.poly())
        ko = shapely.union_all(
            [approaches[d] for d in room.doors]
            + [approaches[d.index] for d in lay.doors if d.other == room.index]
        )
        seeds = [lay.doors[d].point(0.9) for d in room.doors]
        seeds += [d.point(-0.9) for d in lay.doors if d.other == room.index]
        grid = Grid.over(shapely.bounds(room.rect.poly()), _RASTER)
        grid.free = grid.mask(allowed)
        sp = Space(
            room.index,
            room.kind,
            room.rect,
            room.inner,
            prep(allowed),
            prep(ko),
            None,
            0.0,
            seeds,
            grid,
        )
        sp.occupied = np.zeros(grid.shape, bool)
        sp.walls = walls
        spaces.append(sp)
    for k, (rect, is_hall) in enumerate(zip(lay.corridors, lay.hall, strict=True)):
        inner = Rect(*(v for v in _corridor_inner(lay, rect)))
        allowed = free.intersection(rect.poly())
        sp = Space(
            -1 - k,
            "hall" if is_hall else "corridor",
            rect,
            inner,
            prep(allowed),
            prep(ap_all) if ap_all is not None else None,
            graph,
            HALL_RESERVE if is_hall else CORRIDOR_RESERVE,
            [],
            None,
        )
        if is_hall:
            grid = Grid.over(shapely.bounds(rect.poly()), _RASTER)
            grid.free = grid.mask(allowed)
            sp.grid = grid
            sp.occupied = np.zeros(grid.shape, bool)
            sp.seeds = [np.asarray(lay.graph[0][0])]
        spaces.append(sp)
    return spaces


def _corridor_inner(lay: Layout, r: Rect) -> tuple[float, float, float, float]:
    def half(axis: int, c: float) -> float:
        ext = lay.height if axis == 0 else lay.width
        if abs(c) < 1e-6 or abs(c - ext) < 1e-6:
            return lay.t_out
        return lay.thickness.get(line_key(axis, c), 0.0) / 2.0

    return (r.x0 + half(1, r.x0), r.y0 + half(0, r.y0), r.x1 - half(1, r.x1), r.y1 - half(0, r.y1))


def furnish(lay: Layout, walls: object, clutter: float, rng) -> list[Item]:
    """Place furniture until ``clutter`` x the floor area inside the walls is covered (or the
    rooms are full). With ``clutter > 0`` one item of every :data:`MUST_HAVE` kind comes
    first (in random rooms)."""
    spaces = make_spaces(lay, walls)
    if clutter <= 0.0:
        return []
    floor = lay.footprint.difference(walls).area
    target = clutter * floor
    rooms = [s for s in spaces if s.index >= 0]
    halls = [s for s in spaces if s.kind == "hall"]
    corridors = [s for s in spaces if s.kind == "corridor"]
    items: list[Item] = []
    counter = [0]

    def name(item: str) -> str:
        counter[0] += 1
        return f"{item}-{counter[0]}"

    order = list(rng.permutation(len(rooms)))
    for k, item in enumerate(MUST_HAVE):
        for j in range(len(rooms)):
            sp = rooms[order[(k + j) % len(rooms)]]
            it = try_place(sp, item, rng, name(item), tries=16)
            if it is not None:
                items.append(it)
                break
    # corridors and halls: a lighter share of the density
    for sp in corridors + halls:
        share = 0.35 if sp.kind == "hall" else 0.12
        budget = share * clutter * sp.rect.w * sp.rect.h
        items.extend(_fill(sp, budget, rng, name))
    placed = sum(it.area for it in items)
    room_area = np.array([s.inner.w * s.inner.h for s in rooms])
    weight = room_area * rng.uniform(0.6, 1.4, len(rooms))
    weight *= np.array([1.4 if s.kind == "storage" else 1.0 for s in rooms])
    remaining = max(0.0, target - placed)
    for i in rng.permutation(len(rooms)):
        sp = rooms[i]
        share = weight[i] / max(weight.sum(), 1e-9)
        new = _fill(sp, remaining * share, rng, name)
        items.extend(new)
        remaining = max(0.0, remaining - sum(it.area for it in new))
        weight[i] = 0.0
    return items


def _fill(sp: Space, budget: float, rng, name) -> list[Item]:
    recipe = RECIPES[sp.kind]
    keys = list(recipe)
    p = np.asarray([recipe[k] for k in keys], float)
    p /= p.sum()
    out: list[Item] = []
    area, fails = 0.0, 0
    while area < budget and fails < 10:
        item = keys[int(rng.choice(len(keys), p=p))]
        it = try_place(sp, item, rng, name(item), tries=5)
        if it is None:
            fails += 1
            continue
        out.append(it)
        area += it.area
    return out
