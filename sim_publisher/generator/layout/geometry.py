"""Corridor and room geometry of a layout.

The corridor shapes (``_straight``, ``_l_shape``, ``_ring``, ``_atrium``, by name in
``LAYOUT_FUNCS``) draw, in the canonical frame (short side along x), the corridors (or hall),
the blocks left for rooms and the route graph; ``block_rooms`` tiles a block (already in the
map frame) with rooms, its cuts from :func:`split_length`. ``side_contacts`` finds where rectangles
touch (also used for doors and wall thicknesses, :mod:`.walls`).
"""

from __future__ import annotations

import math

import numpy as np

from sim_publisher.generator.layout.types import EPS, MIN_DEPTH, Rect
from sim_publisher.generator.params import TypeSpec


# --------------------------------------------------------------------------- helpers
def uniform_in(rng: np.random.Generator, lo_hi: tuple[float, float]) -> float:
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
    return (lo, hi) if hi - lo > EPS else None


def side_contacts(r: Rect, others: list[Rect]) -> list[tuple[int, float, float, int]]:
    """Where ``r``'s sides touch the opposite sides of ``others``: ``(side, lo, hi, j)``."""
    out = []
    for k in range(4):
        axis, c, lo, hi = r.side(k)
        opp = k ^ 1
        for j, o in enumerate(others):
            oaxis, oc, olo, ohi = o.side(opp)
            if oaxis == axis and abs(oc - c) < EPS:
                ov = _overlap(lo, hi, olo, ohi)
                if ov:
                    out.append((k, ov[0], ov[1], j))
    return out


# --------------------------------------------------------------------------- layouts
def _straight(W, H, spec, rng):
    c = uniform_in(rng, spec.corridor)
    avail = W - c
    a = float(np.clip(avail * rng.uniform(0.35, 0.65), MIN_DEPTH, avail - MIN_DEPTH))
    y0, y1, blocks = 0.0, H, []
    dmax = min(spec.room_depth[1], 6.5)
    if H >= 14.0 and rng.random() < 0.5:
        e = float(np.clip(uniform_in(rng, spec.room_depth), MIN_DEPTH + 0.4, min(dmax, 0.3 * H)))
        blocks.append(Rect(0.0, H - e, W, H))
        y1 = H - e
    if H >= 20.0 and rng.random() < 0.3:
        e = float(np.clip(uniform_in(rng, spec.room_depth), MIN_DEPTH + 0.4, min(dmax, 0.25 * H)))
        blocks.append(Rect(0.0, 0.0, W, e))
        y0 = e
    corridors = [Rect(a, y0, a + c, y1)]
    blocks += [Rect(0.0, y0, a, y1), Rect(a + c, y0, W, y1)]
    xm = a + c / 2
    graph = [np.array([[xm, y0 + c / 2], [xm, y1 - c / 2]])]
    return corridors, [False], blocks, graph


def _l_shape(W, H, spec, rng):
    c = uniform_in(rng, spec.corridor)
    a = float(np.clip(uniform_in(rng, spec.room_depth), MIN_DEPTH, max(MIN_DEPTH, 0.4 * W)))
    a = min(a, W - c - MIN_DEPTH)
    yb = float(np.clip(uniform_in(rng, spec.room_depth), MIN_DEPTH, max(MIN_DEPTH, 0.35 * H)))
    top = H
    blocks = []
    if H - yb - c >= 2 * MIN_DEPTH + 4.0 and rng.random() < 0.5:
        e = float(np.clip(uniform_in(rng, spec.room_depth), MIN_DEPTH + 0.4, 0.25 * H))
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
    c = uniform_in(rng, spec.corridor)
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


LAYOUT_FUNCS = {"straight": _straight, "L": _l_shape, "ring": _ring, "atrium": _atrium}


# --------------------------------------------------------------------------- rooms
def block_rooms(block: Rect, spaces: list[Rect], spec: TypeSpec, rng) -> list[Rect]:
    """Tile a block with rooms: rows parallel to its side with the longest corridor contact
    (deep blocks get several rows, the back ones reached through the front ones); all rows
    share the same cuts along the side, and neighbouring cells of a row may merge."""
    contact = np.zeros(4)
    for k, lo, hi, _ in side_contacts(block, spaces):
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
