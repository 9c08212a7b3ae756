"""Floor layout: footprint, corridors, rooms, doors and walls of varied thickness.

Everything is in the map frame (metres), x right, y up, the footprint ``[0, W] x [0, H]``
(outer faces of the outer walls). Rooms and corridors are axis-aligned rectangles whose edges
are wall **centre lines** (except on the footprint boundary, where the outer wall lies inside).
Walls are built as the union of a band per room edge (its line's thickness), a post at every
room corner (the intersection of the two bands) and the outer frame, minus the door gaps, so
junctions of walls of different thickness are exact.

A layout is first drawn in a canonical frame (short side along x, corridor system fixed up to a
mirror), then mirrored and transposed to the requested footprint.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import shapely
from shapely.geometry import Polygon, box

from service.errors import InvalidWorld
from sim_publisher.generator.params import TYPE_SPECS, TypeSpec

_EPS = 1e-6
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


def _door(index, center, axis, width, thickness, room, other, normal) -> Door:
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


# --------------------------------------------------------------------------- helpers
def _u(rng: np.random.Generator, lo_hi: tuple[float, float]) -> float:
    return float(rng.uniform(lo_hi[0], lo_hi[1]))


def split_length(
    L: float, lo: float, hi: float, rng: np.random.Generator, jitter: float = 0.25
) -> list[float]:
    """Split ``L`` (m) into parts of roughly ``[lo, hi]`` m (at least one part)."""
    n_min = max(1, math.ceil(L / hi - 1e-9))
    n_max = max(1, math.floor(L / lo + 1e-9))
    n = n_min if n_max < n_min else int(rng.integers(n_min, n_max + 1))
    w = rng.uniform(1.0 - jitter, 1.0 + jitter, n)
    return list(L * w / w.sum())


def _overlap(a0: float, a1: float, b0: float, b1: float) -> tuple[float, float] | None:
    lo, hi = max(a0, b0), min(a1, b1)
    return (lo, hi) if hi - lo > _EPS else None


def _contacts(r: Rect, others: list[Rect]) -> list[tuple[int, float, float, int]]:
    """Where ``r``'s sides touch the opposite sides of ``others``: ``(side, lo, hi, j)``."""
    out = []
    for k in range(4):
        axis, c, lo, hi = r.side(k)
        opp = k ^ 1
        for j, o in enumerate(others):
            oaxis, oc, olo, ohi = o.side(opp)
            if oaxis == axis and abs(oc - c) < _EPS:
                ov = _overlap(lo, hi, olo, ohi)
                if ov:
                    out.append((k, ov[0], ov[1], j))
    return out


# --------------------------------------------------------------------------- layouts
def _straight(W, H, spec, rng):
    c = _u(rng, spec.corridor)
    avail = W - c
    a = float(np.clip(avail * rng.uniform(0.35, 0.65), MIN_DEPTH, avail - MIN_DEPTH))
    y0, y1, blocks = 0.0, H, []
    dmax = min(spec.room_depth[1], 6.5)
    if H >= 14.0 and rng.random() < 0.5:
        e = float(np.clip(_u(rng, spec.room_depth), MIN_DEPTH + 0.4, min(dmax, 0.3 * H)))
        blocks.append(Rect(0.0, H - e, W, H))
        y1 = H - e
    if H >= 20.0 and rng.random() < 0.3:
        e = float(np.clip(_u(rng, spec.room_depth), MIN_DEPTH + 0.4, min(dmax, 0.25 * H)))
        blocks.append(Rect(0.0, 0.0, W, e))
        y0 = e
    corridors = [Rect(a, y0, a + c, y1)]
    blocks += [Rect(0.0, y0, a, y1), Rect(a + c, y0, W, y1)]
    xm = a + c / 2
    graph = [np.array([[xm, y0 + c / 2], [xm, y1 - c / 2]])]
    return corridors, [False], blocks, graph


def _l_shape(W, H, spec, rng):
    c = _u(rng, spec.corridor)
    a = float(np.clip(_u(rng, spec.room_depth), MIN_DEPTH, max(MIN_DEPTH, 0.4 * W)))
    a = min(a, W - c - MIN_DEPTH)
    yb = float(np.clip(_u(rng, spec.room_depth), MIN_DEPTH, max(MIN_DEPTH, 0.35 * H)))
    top = H
    blocks = []
    if H - yb - c >= 2 * MIN_DEPTH + 4.0 and rng.random() < 0.5:
        e = float(np.clip(_u(rng, spec.room_depth), MIN_DEPTH + 0.4, 0.25 * H))
        top = H - e
        blocks.append(Rect(a, top, W, H))
    corridors = [Rect(a, yb, a + c, top), Rect(a, yb, W, yb + c)]
    blocks += [Rect(0.0, yb, a, H), Rect(0.0, 0.0, W, yb), Rect(a + c, yb + c, W, top)]
    xm, ym = a + c / 2, yb + c / 2
    graph = [np.array([[xm, top - c / 2], [xm, ym], [W - c / 2, ym]])]
    return corridors, [False, False], blocks, graph


def _bands(W, H, spec, rng, inner_min, inner_max):
    """Depths (left, right, bottom, top) of the outer band of rooms around a central area
    whose sides end up in ``[inner_min, inner_max]`` where possible."""
    out = []
    for ext in (W, W, H, H):
        lo = max(MIN_DEPTH, (ext - inner_max) / 2.0)
        hi = max(lo, min(max(spec.room_depth[1], lo), (ext - inner_min) / 2.0))
        out.append(float(rng.uniform(lo, hi)) if hi > lo else lo)
    dl, dr, db, dt = out
    return dl, dr, db, dt


def _outer_blocks(W, H, dl, dr, db, dt) -> list[Rect]:
    return [
        Rect(0.0, 0.0, W, db),
        Rect(0.0, H - dt, W, H),
        Rect(0.0, db, dl, H - dt),
        Rect(W - dr, db, W, H - dt),
    ]


def _loop(x0, y0, x1, y1) -> np.ndarray:
    return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1], [x0, y0]])


def _ring(W, H, spec, rng):
    c = _u(rng, spec.corridor)
    core_min = 3.2
    if W - 2 * c - core_min < 2 * MIN_DEPTH:
        c = max(1.8, (W - core_min - 2 * MIN_DEPTH) / 2.0)
    dl, dr, db, dt = _bands(W, H, spec, rng, 2 * c + core_min, 2 * c + 24.0)
    corridors = [
        Rect(dl, db, W - dr, db + c),
        Rect(dl, H - dt - c, W - dr, H - dt),
        Rect(dl, db, dl + c, H - dt),
        Rect(W - dr - c, db, W - dr, H - dt),
    ]
    blocks = [*_outer_blocks(W, H, dl, dr, db, dt), Rect(dl + c, db + c, W - dr - c, H - dt - c)]
    graph = [_loop(dl + c / 2, db + c / 2, W - dr - c / 2, H - dt - c / 2)]
    return corridors, [False] * 4, blocks, graph


def _atrium(W, H, spec, rng):
    dl, dr, db, dt = _bands(W, H, spec, rng, 6.5, 18.0)
    hall = Rect(dl, db, W - dr, H - dt)
    g = min(1.5, hall.w / 4.0, hall.h / 4.0)
    graph = [_loop(hall.x0 + g, hall.y0 + g, hall.x1 - g, hall.y1 - g)]
    return [hall], [True], _outer_blocks(W, H, dl, dr, db, dt), graph


_LAYOUT_FUNCS = {"straight": _straight, "L": _l_shape, "ring": _ring, "atrium": _atrium}


# --------------------------------------------------------------------------- rooms
def _block_rooms(block: Rect, spaces: list[Rect], spec: TypeSpec, rng) -> list[Rect]:
    """Tile a block with rooms: rows parallel to its side with the longest corridor contact
    (deep blocks get several rows, the back ones reached through the front ones); all rows
    share the same cuts along the side, and neighbouring cells of a row may merge."""
    contact = np.zeros(4)
    for k, lo, hi, _ in _contacts(block, spaces):
        contact[k] += hi - lo
    if contact.max() <= 0.0:
        contact = np.array([block.h, block.h, block.w, block.w])
    k = int(np.argmax(contact + rng.uniform(0, 1e-3, 4)))
    along_y = k in (0, 1)
    depth = block.w if along_y else block.h
    length = block.h if along_y else block.w
    dmax = spec.room_depth[1]
    n_rows = max(1, math.ceil(depth / dmax - 1e-9))
    rows = split_length(depth, depth / n_rows * 0.999, depth / n_rows * 1.001, rng, 0.15)
    if len(rows) != n_rows:
        rows = [depth / n_rows] * n_rows
    cols = split_length(length, spec.room_width[0], spec.room_width[1], rng)
    edges = np.concatenate([[0.0], np.cumsum(cols)])
    edges[-1] = length
    # rows ordered from the primary side outward
    doff = np.concatenate([[0.0], np.cumsum(rows)])
    doff[-1] = depth
    out = []
    for r in range(n_rows):
        d0, d1 = (doff[r], doff[r + 1])
        if k in (1, 3):  # primary side is the far one: measure from it
            d0, d1 = depth - d1, depth - d0
        i = 0
        while i < len(cols):
            j = i + 1
            while (
                j < len(cols)
                and j - i < 3
                and rng.random() < spec.merge
                and edges[j + 1] - edges[i] <= 1.5 * spec.room_width[1]
            ):
                j += 1
            a0, a1 = edges[i], edges[j]
            if along_y:
                out.append(Rect(block.x0 + d0, block.y0 + a0, block.x0 + d1, block.y0 + a1))
            else:
                out.append(Rect(block.x0 + a0, block.y0 + d0, block.x0 + a1, block.y0 + d1))
            i = j
    return out


def _line_key(axis: int, c: float) -> tuple[int, float]:
    return axis, round(c, 6)


def _on_boundary(axis: int, c: float, W: float, H: float) -> bool:
    ext = H if axis == 0 else W
    return abs(c) < _EPS or abs(c - ext) < _EPS


def _door_slot(lo, hi, width, used, rng, margin) -> float | None:
    """A door centre in ``[lo, hi]`` leaving ``margin`` to the ends and 0.6 m to ``used``."""
    a, b = lo + margin + width / 2.0, hi - margin - width / 2.0
    if b < a:
        return None
    for _ in range(12):
        s = float(rng.uniform(a, b))
        if all(abs(s - u) > (width + w2) / 2.0 + 0.6 for u, w2 in used):
            return s
    return None


def _door_width(spec: TypeSpec, bounds: tuple[float, float], rng) -> float:
    if rng.random() < spec.double_door:
        w = rng.uniform(1.4, 1.8)
    elif rng.random() < 0.08:
        w = rng.uniform(0.8, 0.86)
    else:
        w = _u(rng, spec.door)
    return float(np.clip(w, bounds[0], bounds[1]))


def build_layout(
    W: float,
    H: float,
    layout: str,
    building_type: str,
    rng: np.random.Generator,
    door_bounds: tuple[float, float] = (0.8, 1.8),
    wall_bounds: tuple[float, float] = (0.1, 0.3),
) -> Layout:
    """Draw a building shell of ``W`` x ``H`` m (without wall details: see
    :func:`sim_publisher.generator.details.wall_details`). Raises InvalidWorld if the layout
    cannot fit."""
    spec = TYPE_SPECS[building_type]
    transpose = W > H
    Wc, Hc = (H, W) if transpose else (W, H)
    corridors, hall, blocks, graph = _LAYOUT_FUNCS[layout](Wc, Hc, spec, rng)
    for b in blocks + corridors:
        if b.w < MIN_DEPTH - 1e-6 or b.h < MIN_DEPTH - 1e-6:
            if b in corridors and min(b.w, b.h) >= 1.5:
                continue
            raise InvalidWorld(
                f"generator: a {layout} layout does not fit a {W:.1f} x {H:.1f} m footprint "
                f"(a block of {b.w:.1f} x {b.h:.1f} m)"
            )
    fx, fy = bool(rng.random() < 0.5), bool(rng.random() < 0.5)
    corridors = [r.mirrored(Wc, Hc, fx, fy) for r in corridors]
    blocks = [r.mirrored(Wc, Hc, fx, fy) for r in blocks]
    graph = [np.c_[Wc - g[:, 0] if fx else g[:, 0], Hc - g[:, 1] if fy else g[:, 1]] for g in graph]
    if transpose:
        corridors = [r.transposed() for r in corridors]
        blocks = [r.transposed() for r in blocks]
        graph = [g[:, ::-1].copy() for g in graph]
    rects: list[Rect] = []
    for b in blocks:
        rects.extend(_block_rooms(b, corridors, spec, rng))
    kinds, weights = zip(*spec.rooms, strict=True)
    p = np.asarray(weights) / np.sum(weights)
    rooms = [Room(i, r, str(kinds[rng.choice(len(kinds), p=p)])) for i, r in enumerate(rects)]
    thickness, t_out = _thicknesses(rooms, corridors, W, H, wall_bounds, rng)
    for room in rooms:
        room.inner = _inner(room.rect, thickness, t_out, W, H)
    doors = _doors(rooms, corridors, thickness, spec, door_bounds, rng)
    core = _wall_core(rooms, thickness, t_out, W, H)
    lay = Layout(
        W,
        H,
        layout,
        building_type,
        corridors,
        hall,
        rooms,
        doors,
        graph,
        t_out,
        thickness,
        core,
        [],
    )
    return lay


def _thicknesses(rooms, corridors, W, H, bounds, rng):
    lo, hi = bounds
    t_out = float(rng.uniform(lo + 0.5 * (hi - lo), hi))
    corridor_lines = set()
    for room in rooms:
        for k, *_ in _contacts(room.rect, corridors):
            axis, c, _, _ = room.rect.side(k)
            corridor_lines.add(_line_key(axis, c))
    thickness: dict[tuple[int, float], float] = {}
    for room in rooms:
        for k in range(4):
            axis, c, _, _ = room.rect.side(k)
            key = _line_key(axis, c)
            if key in thickness or _on_boundary(axis, c, W, H):
                continue
            if key in corridor_lines:
                t = rng.uniform(lo + 0.2 * (hi - lo), lo + 0.8 * (hi - lo))
            else:
                t = rng.uniform(lo, lo + 0.6 * (hi - lo))
            thickness[key] = float(t)
    return thickness, t_out


def _half(axis, c, thickness, t_out, W, H) -> float:
    if _on_boundary(axis, c, W, H):
        return t_out
    return thickness[_line_key(axis, c)] / 2.0


def _inner(r: Rect, thickness, t_out, W, H) -> Rect:
    return Rect(
        r.x0 + _half(1, r.x0, thickness, t_out, W, H),
        r.y0 + _half(0, r.y0, thickness, t_out, W, H),
        r.x1 - _half(1, r.x1, thickness, t_out, W, H),
        r.y1 - _half(0, r.y1, thickness, t_out, W, H),
    )


def _doors(rooms, corridors, thickness, spec, bounds, rng) -> list[Door]:
    doors: list[Door] = []
    used: dict[tuple[int, float], list[tuple[float, float]]] = {}
    rects = [r.rect for r in rooms]
    tmax = max(thickness.values(), default=0.2)
    margin = JAMB_MIN + tmax / 2.0

    def add(room: Room, k: int, lo: float, hi: float, other: int) -> bool:
        axis, c, _, _ = room.rect.side(k)
        key = _line_key(axis, c)
        w = _door_width(spec, bounds, rng)
        s = None
        while s is None and w >= bounds[0] - 1e-9:
            s = _door_slot(lo, hi, w, used.setdefault(key, []), rng, margin)
            if s is None:
                w -= 0.1
        if s is None:
            return False
        used[key].append((s, w))
        center = (s, c) if axis == 0 else (c, s)
        sign = 1.0 if k in (0, 2) else -1.0  # normal into the room
        normal = (0.0, sign) if axis == 0 else (sign, 0.0)
        d = _door(len(doors), center, axis, w, thickness[key], room.index, other, normal)
        doors.append(d)
        room.doors.append(d.index)
        return True

    connected = np.zeros(len(rooms), bool)
    for room in rooms:
        cont = _contacts(room.rect, corridors)
        if not cont:
            continue
        by_side: dict[int, list[tuple[float, float]]] = {}
        for k, lo, hi, _ in cont:
            by_side.setdefault(k, []).append((lo, hi))
        merged = []
        for k, ivs in by_side.items():
            ivs.sort()
            cur = list(ivs[0])
            for lo, hi in ivs[1:]:
                if lo <= cur[1] + _EPS:
                    cur[1] = max(cur[1], hi)
                else:
                    merged.append((k, *cur))
                    cur = [lo, hi]
            merged.append((k, *cur))
        merged.sort(key=lambda m: m[2] - m[1], reverse=True)
        if add(room, *merged[0], -1):
            connected[room.index] = True
            extra = merged[1:] if len(merged) > 1 else merged
            if rng.random() < 0.25:
                k, lo, hi = extra[int(rng.integers(len(extra)))]
                add(room, k, lo, hi, -1)
    adj: list[list[tuple[int, int, float, float]]] = [[] for _ in rooms]
    for room in rooms:
        for k, lo, hi, j in _contacts(room.rect, rects):
            if j != room.index:
                adj[room.index].append((j, k, lo, hi))
    changed = True
    while not connected.all() and changed:
        changed = False
        for room in rooms:
            if connected[room.index]:
                continue
            opts = [a for a in adj[room.index] if connected[a[0]]]
            opts.sort(key=lambda a: a[3] - a[2], reverse=True)
            for j, k, lo, hi in opts:
                if add(room, k, lo, hi, j):
                    connected[room.index] = True
                    changed = True
                    break
    if not connected.all():
        bad = [r.index for r in rooms if not connected[r.index]]
        raise InvalidWorld(f"generator: rooms {bad} cannot be reached through a door")
    for room in rooms:  # a few extra connecting doors between neighbouring rooms
        if rng.random() < 0.12 and adj[room.index]:
            j, k, lo, hi = adj[room.index][int(rng.integers(len(adj[room.index])))]
            if not any(doors[d].other == j for d in room.doors):
                add(room, k, lo, hi, j)
    return doors


def _wall_core(rooms, thickness, t_out, W, H):
    parts = [box(0, 0, W, H).difference(box(t_out, t_out, W - t_out, H - t_out))]
    for room in rooms:
        r = room.rect
        half = {}
        for k in range(4):
            axis, c, lo, hi = r.side(k)
            if _on_boundary(axis, c, W, H):
                half[k] = None
                continue
            t2 = thickness[_line_key(axis, c)] / 2.0
            half[k] = t2
            if axis == 0:
                parts.append(box(lo, c - t2, hi, c + t2))
            else:
                parts.append(box(c - t2, lo, c + t2, hi))
        for kx, ky in ((0, 2), (0, 3), (1, 2), (1, 3)):
            if half[kx] is None or half[ky] is None:
                continue
            x = r.x0 if kx == 0 else r.x1
            y = r.y0 if ky == 2 else r.y1
            parts.append(box(x - half[kx], y - half[ky], x + half[kx], y + half[ky]))
    return shapely.union_all(parts)
