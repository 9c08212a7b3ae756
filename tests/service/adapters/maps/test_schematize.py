"""Schematisation: long walls stay (within a stated distance), small objects and clutter go,
corners are simplified by DCE (fewer vertices), doors stay open, occlusion gaps close."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pydantic
import pytest
import shapely

from service.adapters.maps.schematize import SchematizeParams, schematize
from service.core.types import MapData
from service.errors import InvalidMessage

#: The room's walls (metres): a 10 x 6 m room, a 0.9 m door in the top wall between x = 4.0
#: and 4.9, a 4 cm deep, 0.3 m wide niche in the bottom wall at x = 6.0 .. 6.3.
ROOM = np.array(
    [
        [4.0, 6.0],
        [0.0, 6.0],
        [0.0, 0.0],
        [6.0, 0.0],
        [6.0, -0.04],
        [6.3, -0.04],
        [6.3, 0.0],
        [10.0, 0.0],
        [10.0, 6.0],
        [4.9, 6.0],
    ]
)
#: Clutter: a 0.6 x 0.4 m box seen all round, the 0.8 m L-shaped front of a desk, a 0.3 m
#: stray piece (all away from the walls).
BOX = np.array([[3.0, 3.0], [3.6, 3.0], [3.6, 3.4], [3.0, 3.4], [3.0, 3.0]])
DESK = np.array([[7.0, 2.0], [7.5, 2.0], [7.5, 2.3]])
STRAY = np.array([[2.0, 1.5], [2.3, 1.5]])
NOISE = 0.01  # vertex noise (m), as a built map's ridge has


def _densify(poly: np.ndarray, step: float) -> np.ndarray:
    out = [poly[:1]]
    for a, b in itertools.pairwise(poly):
        n = max(math.ceil(float(np.hypot(*(b - a))) / step), 1)
        out.append(a + (b - a) * (np.arange(1, n + 1)[:, None] / n))
    return np.vstack(out)


def _metric_map() -> MapData:
    """The room as a metric map would draw it: vertices every 5 cm with 1 cm noise, the left
    wall broken by a 0.3 m occlusion gap (y = 2.0 .. 2.3), plus the clutter."""
    rng = np.random.default_rng(11)
    walls = _densify(ROOM, 0.05)
    walls = walls + rng.normal(0.0, NOISE, walls.shape)
    # split the left wall (x ~ 0) at the occlusion
    on_left = (np.abs(walls[:, 0]) < 0.05) & (walls[:, 1] > 2.0) & (walls[:, 1] < 2.3)
    cut = np.nonzero(on_left)[0]
    a, b = walls[: cut[0]], walls[cut[-1] + 1 :]
    clutter = [_densify(q, 0.05) for q in (BOX, DESK, STRAY)]
    clutter = [q + rng.normal(0.0, NOISE, q.shape) for q in clutter]
    return MapData.from_lists("room", "metric", [a, b, *clutter])


def _lines(m: MapData) -> shapely.MultiLineString:
    return shapely.MultiLineString([shapely.LineString(p) for p in m.polylines])


def test_keeps_walls_drops_clutter_fewer_vertices() -> None:
    metric = _metric_map()
    s = schematize(metric)
    assert s.kind == "schematic" and s.map_id == "room"
    n_in = sum(p.shape[0] for p in metric.polylines)
    n_out = sum(p.shape[0] for p in s.polylines)
    assert n_in > 600
    assert n_out <= 8  # measured 6: the door jambs and the four corners (the gap is joined)
    # every point of the result is within 5 cm of the true walls: no clutter, no stray corner
    truth = shapely.LineString(ROOM)
    pts = np.vstack([_densify(p, 0.02) for p in s.polylines])
    d = shapely.distance(truth, shapely.points(pts))
    assert d.max() < 0.05
    # the walls are all there: the true walls (sampled every 5 cm) lie within 5 cm of the
    # result, except the niche (flattened: 4 cm deep)
    back = shapely.distance(_lines(s), shapely.points(_densify(ROOM, 0.05)))
    assert back.max() < 0.06
    # the 0.3 m occlusion gap in the left wall is closed, the 0.9 m door stays open
    assert shapely.distance(_lines(s), shapely.Point(0.0, 2.15)) < 0.03
    assert shapely.distance(_lines(s), shapely.Point(4.45, 6.0)) > 0.4


def test_niche_and_corners_are_simplified_by_dce() -> None:
    s = schematize(_metric_map())
    verts = np.vstack(s.polylines)
    # no vertex stays at the 4 cm niche (bump of relevance ~0.08 m < 0.15 m)
    near_niche = (verts[:, 0] > 5.9) & (verts[:, 0] < 6.4) & (verts[:, 1] < 0.5)
    assert not near_niche.any()
    # each of the room's four corners is kept as one vertex within 3 cm of the true corner
    for c in ([0.0, 0.0], [10.0, 0.0], [10.0, 6.0], [0.0, 6.0]):
        dist = np.hypot(*(verts - np.array(c)).T)
        assert np.sum(dist < 0.2) == 1 and dist.min() < 0.03


def test_parameters_change_what_is_kept() -> None:
    metric = _metric_map()
    # no size filter: the box, the desk and the stray piece stay (the stray one only with
    # min_length 0: it is short and attached to nothing)
    keep_all = schematize(
        metric, SchematizeParams(min_extent=0.0, min_ring_extent=0.0, min_length=0.0)
    )
    lines = _lines(keep_all)
    for q in (BOX, DESK, STRAY):
        assert shapely.distance(lines, shapely.Point(*q.mean(axis=0))) < 0.35
    # relevance 0: no DCE, so many more vertices, still on the walls
    raw = schematize(metric, SchematizeParams(relevance=0.0))
    assert sum(p.shape[0] for p in raw.polylines) > 400
    # merge_gap 0 and snap 0: the occlusion gap stays open
    open_gap = schematize(metric, SchematizeParams(merge_gap=0.0, snap=0.0))
    assert shapely.distance(_lines(open_gap), shapely.Point(0.0, 2.15)) > 0.1
    # max_deviation guards a long gentle arc against DCE's chord
    t = np.linspace(0.0, math.pi, 241)
    arc = np.column_stack((6.0 * np.cos(t), 0.5 * np.sin(t)))  # 12 m wide, bowed by 0.5 m
    arc_map = MapData.from_lists("arc", "metric", [arc])
    guarded = schematize(arc_map, SchematizeParams(relevance=0.3, max_deviation=0.05))
    chord = schematize(arc_map, SchematizeParams(relevance=0.3, max_deviation=0.0))
    d_g = shapely.distance(_lines(guarded), shapely.points(arc)).max()
    d_c = shapely.distance(_lines(chord), shapely.points(arc)).max()
    assert d_g <= 0.05 + 1e-9 and d_c > 0.3


def test_nothing_left_and_bad_parameters() -> None:
    clutter = MapData.from_lists("c", "metric", [BOX, DESK])
    with pytest.raises(InvalidMessage, match="nothing of map 'c' survives"):
        schematize(clutter)
    with pytest.raises(pydantic.ValidationError):
        SchematizeParams(min_extent=-1.0)
    with pytest.raises(pydantic.ValidationError):
        SchematizeParams(merge_angle=120.0)
    with pytest.raises(pydantic.ValidationError):
        SchematizeParams(unknown=1.0)  # type: ignore[call-arg]
