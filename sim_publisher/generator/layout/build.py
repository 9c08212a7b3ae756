"""``build_layout``: a building shell of a given footprint, layout and building type.

The layout is first drawn in a canonical frame (short side along x, corridor system fixed up
to a mirror, :mod:`.geometry`), then mirrored and transposed to the requested footprint; the
blocks are tiled with rooms, and the wall thicknesses, inner faces, doors and wall core are
drawn (:mod:`.walls`).
"""

from __future__ import annotations

import numpy as np

from service.errors import InvalidWorld
from sim_publisher.generator.layout.geometry import LAYOUT_FUNCS, block_rooms
from sim_publisher.generator.layout.types import MIN_DEPTH, Layout, Rect, Room
from sim_publisher.generator.layout.walls import (
    inner_rect,
    place_doors,
    wall_core,
    wall_thicknesses,
)
from sim_publisher.generator.params import TYPE_SPECS


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
    corridors, hall, blocks, graph = LAYOUT_FUNCS[layout](Wc, Hc, spec, rng)
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
        rects.extend(block_rooms(b, corridors, spec, rng))
    kinds, weights = zip(*spec.rooms, strict=True)
    p = np.asarray(weights) / np.sum(weights)
    rooms = [Room(i, r, str(kinds[rng.choice(len(kinds), p=p)])) for i, r in enumerate(rects)]
    thickness, t_out = wall_thicknesses(rooms, corridors, W, H, wall_bounds, rng)
    for room in rooms:
        room.inner = inner_rect(room.rect, thickness, t_out, W, H)
    doors = place_doors(rooms, corridors, thickness, spec, door_bounds, rng)
    core = wall_core(rooms, thickness, t_out, W, H)
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
