"""The office world and its metric and schematic maps."""

from __future__ import annotations

import json

import numpy as np
import pytest
import shapely
from shapely.geometry import LineString, Point

from service.adapters.convert import map_message_of
from sim_publisher.office import office_metric_map, office_schematic_map, office_world


def _by_name(name: str):
    return next(o for o in office_world().obstacles if o.name == name)


def test_office_extent_walls_and_furniture() -> None:
    w = office_world()
    assert w.bounds == (0.0, 0.0, 14.0, 23.0)
    kinds = {o.kind for o in w.obstacles}
    assert {"wall", "furniture", "complex", "circle"} <= kinds
    assert sum(o.kind != "wall" for o in w.obstacles) >= 15
    # Seven rooms + corridor: interior free space splits into >= 6 pieces once doors are closed.
    walls = shapely.union_all([o.geometry for o in w.obstacles if o.kind == "wall"])
    doors = shapely.union_all(
        [LineString([(5.5, y), (5.7, y)]).buffer(0.5) for y in (3.0, 7.6, 10.6, 14.5, 19.8)]
        + [LineString([(7.5, y), (7.7, y)]).buffer(0.5) for y in (4.0, 11.5, 18.5)]
        + [Point(11.0, 15.0).buffer(0.5)]
    )
    rooms = shapely.box(0.15, 0.15, 13.85, 22.85).difference(walls.union(doors))
    big = [g for g in getattr(rooms, "geoms", [rooms]) if g.area > 5.0]
    assert len(big) >= 8  # 7 rooms and the corridor


def test_pillar_is_a_fine_circle_near_the_top_left_wall() -> None:
    g = _by_name("pillar-L4").geometry
    assert len(g.exterior.coords) - 1 >= 48
    c = np.asarray(g.centroid.coords[0])
    radius = np.hypot(*(np.asarray(g.exterior.coords) - c).T)
    assert 0.3 <= radius.mean() <= 0.5 and np.ptp(radius) < 1e-3
    assert c[0] < 5.6 and c[1] > 17.0  # top-left room
    wall_geoms = [o.geometry for o in office_world().obstacles if o.kind == "wall"]
    gap = min(g.distance(wg) for wg in wall_geoms)
    assert 0.3 <= gap <= 0.6


def test_metric_map_is_the_world_rings() -> None:
    md = office_metric_map()
    w = office_world()
    assert md.kind == "metric" and md.map_id == "office"
    assert len(md.polylines) == len(w.rings())
    assert md.segments().shape == w.segments().shape
    for p in md.polylines:
        np.testing.assert_array_equal(p[0], p[-1])


def test_schematic_has_outlines_only_with_door_gaps_and_jitter() -> None:
    md = office_schematic_map()
    assert md.kind == "schematic" and md.map_id == "office-schematic"
    assert len(md.polylines) >= 10
    lines = shapely.MultiLineString([p.tolist() for p in md.polylines])
    w = office_world()
    walls = shapely.union_all([o.geometry for o in w.obstacles if o.kind == "wall"])
    pts = np.vstack(md.polylines)
    # Every vertex lies near a wall face (jitter <= 8 cm), none in the middle of a room.
    d = shapely.distance(walls, shapely.points(pts))
    assert d.max() <= 0.08 + 1e-6
    # Corners are displaced: not all vertices sit exactly on a wall.
    assert np.mean(d > 0.005) > 0.3
    # No furniture: the schematic stays away from every non-wall obstacle except where
    # furniture stands close to a wall (>= 4 cm away there too, minus jitter).
    for name in ("blob-L2", "crates-R1", "pillar-L4", "round-table-R3", "table-R2"):
        assert lines.distance(_by_name(name).geometry) > 0.3, name
    # Door gaps stay open: no schematic line crosses a door centre.
    for door in [(5.6, 7.6), (5.6, 10.6), (5.6, 19.8), (7.6, 4.0), (7.6, 18.5)]:
        assert lines.distance(Point(door)) > 0.3, door
    # Details are left out: the niche in the bottom-right room's east wall is not traced.
    assert lines.distance(Point(13.9, 2.8)) > 0.05 - 1e-9


def test_map_message_is_plain_json() -> None:
    for md in (office_metric_map(), office_schematic_map()):
        msg = map_message_of(md, name=md.map_id).to_wire()
        assert set(msg) == {"map_id", "kind", "polylines", "name"}
        assert msg["kind"] == md.kind and msg["name"] == md.map_id
        back = json.loads(json.dumps(msg))
        assert back == msg
        assert all(type(v) is float for p in msg["polylines"] for xy in p for v in xy)
        np.testing.assert_array_equal(np.asarray(msg["polylines"][0]), md.polylines[0])
    assert map_message_of(office_metric_map("o2"), name="Office").to_wire()["name"] == "Office"


def test_plot_helpers_draw_every_polyline(tmp_path) -> None:
    pytest.importorskip("matplotlib")
    from sim_publisher.plot import figure_axes, plot_map, plot_path, plot_world

    fig, ax = figure_axes()
    md = office_schematic_map()
    plot_map(ax, md, color="r")
    assert len(ax.lines) == len(md.polylines)
    plot_path(ax, np.array([[1.0, 1.0, 0.0], [2.0, 2.0, 0.0]]))
    assert len(ax.lines) == len(md.polylines) + 1
    plot_world(ax, office_world())
    assert len(ax.patches) >= len(office_world().obstacles)
    out = tmp_path / "f.png"
    fig.savefig(out)
    assert out.stat().st_size > 1000
