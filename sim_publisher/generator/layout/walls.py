"""Walls and doors of a layout: one thickness per wall line (``wall_thicknesses``, keyed by
``line_key``), the rooms' inner faces (``inner_rect``), the doors (``place_doors``: every room
reachable, each door's width drawn, its slot kept clear of the other doors on its wall line)
and the wall core (``wall_core``).

Walls are built as the union of a band per room edge (its line's thickness), a post at every
room corner (the intersection of the two bands) and the outer frame; the door gaps are cut out
later (:meth:`Layout.walls`), so junctions of walls of different thickness are exact.
"""

from __future__ import annotations

import numpy as np
import shapely
from shapely.geometry import box

from service.errors import InvalidWorld
from sim_publisher.generator.layout.geometry import side_contacts, uniform_in
from sim_publisher.generator.layout.types import EPS, JAMB_MIN, Door, Rect, Room, make_door
from sim_publisher.generator.params import TypeSpec


def line_key(axis: int, c: float) -> tuple[int, float]:
    return axis, round(c, 6)


def on_boundary(axis: int, c: float, W: float, H: float) -> bool:
    ext = H if axis == 0 else W
    return abs(c) < EPS or abs(c - ext) < EPS


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
        w = uniform_in(rng, spec.door)
    return float(np.clip(w, bounds[0], bounds[1]))


def wall_thicknesses(rooms, corridors, W, H, bounds, rng):
    lo, hi = bounds
    t_out = float(rng.uniform(lo + 0.5 * (hi - lo), hi))
    corridor_lines = set()
    for room in rooms:
        for k, *_ in side_contacts(room.rect, corridors):
            axis, c, _, _ = room.rect.side(k)
            corridor_lines.add(line_key(axis, c))
    thickness: dict[tuple[int, float], float] = {}
    for room in rooms:
        for k in range(4):
            axis, c, _, _ = room.rect.side(k)
            key = line_key(axis, c)
            if key in thickness or on_boundary(axis, c, W, H):
                continue
            if key in corridor_lines:
                t = rng.uniform(lo + 0.2 * (hi - lo), lo + 0.8 * (hi - lo))
            else:
                t = rng.uniform(lo, lo + 0.6 * (hi - lo))
            thickness[key] = float(t)
    return thickness, t_out


def _half(axis, c, thickness, t_out, W, H) -> float:
    if on_boundary(axis, c, W, H):
        return t_out
    return thickness[line_key(axis, c)] / 2.0


def inner_rect(r: Rect, thickness, t_out, W, H) -> Rect:
    return Rect(
        r.x0 + _half(1, r.x0, thickness, t_out, W, H),
        r.y0 + _half(0, r.y0, thickness, t_out, W, H),
        r.x1 - _half(1, r.x1, thickness, t_out, W, H),
        r.y1 - _half(0, r.y1, thickness, t_out, W, H),
    )


def place_doors(rooms, corridors, thickness, spec, bounds, rng) -> list[Door]:
    doors: list[Door] = []
    used: dict[tuple[int, float], list[tuple[float, float]]] = {}
    rects = [r.rect for r in rooms]
    tmax = max(thickness.values(), default=0.2)
    margin = JAMB_MIN + tmax / 2.0

    def add(room: Room, k: int, lo: float, hi: float, other: int) -> bool:
        axis, c, _, _ = room.rect.side(k)
        key = line_key(axis, c)
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
        d = make_door(len(doors), center, axis, w, thickness[key], room.index, other, normal)
        doors.append(d)
        room.doors.append(d.index)
        return True

    connected = np.zeros(len(rooms), bool)
    for room in rooms:
        cont = side_contacts(room.rect, corridors)
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
                if lo <= cur[1] + EPS:
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
        for k, lo, hi, j in side_contacts(room.rect, rects):
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


def wall_core(rooms, thickness, t_out, W, H):
    parts = [box(0, 0, W, H).difference(box(t_out, t_out, W - t_out, H - t_out))]
    for room in rooms:
        r = room.rect
        half = {}
        for k in range(4):
            axis, c, lo, hi = r.side(k)
            if on_boundary(axis, c, W, H):
                half[k] = None
                continue
            t2 = thickness[line_key(axis, c)] / 2.0
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
