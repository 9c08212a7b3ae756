"""Building generator: determinism, corpus coverage, sizes, reachability, furniture, walls,
doors and the two maps (metric and schematic)."""

from __future__ import annotations

from functools import cache

import numpy as np
import pytest
import shapely
from pydantic import ValidationError
from shapely.geometry import Point, box

from service.errors import InvalidWorld
from sim_publisher.generator import (
    BUILDING_TYPES,
    LAYOUTS,
    OFFICE_CLUTTER,
    Building,
    BuildingParams,
    SchematicParams,
    generate_building,
    resolve_params,
)
from sim_publisher.generator.furniture import MUST_HAVE

TUNING = range(40)


@cache
def building(seed: int) -> Building:
    return generate_building(seed)


def _walls(b: Building):
    return shapely.union_all([o.geometry for o in b.world.obstacles if o.kind == "wall"])


def _furniture(b: Building) -> list:
    return [o.geometry for o in b.world.obstacles if o.kind != "wall"]


# ------------------------------------------------------------------ determinism
def test_same_seed_gives_identical_geometry_maps_and_tours() -> None:
    p = BuildingParams(people=2)
    a, b = generate_building(11, p), generate_building(11, p)
    assert len(a.world.obstacles) == len(b.world.obstacles)
    for ra, rb in zip(a.world.rings(), b.world.rings(), strict=True):
        np.testing.assert_array_equal(ra, rb)
    for pa, pb in zip(a.metric_map().polylines, b.metric_map().polylines, strict=True):
        np.testing.assert_array_equal(pa, pb)
    sa, sb = a.schematic(), b.schematic()
    assert sa.scale == sb.scale
    for pa, pb in zip(sa.map_data.polylines, sb.map_data.polylines, strict=True):
        np.testing.assert_array_equal(pa, pb)
    np.testing.assert_array_equal(a.tour.poses(0.104), b.tour.poses(0.104))
    np.testing.assert_array_equal(a.people_at(12.5), b.people_at(12.5))


def test_different_seeds_give_different_buildings() -> None:
    segs = [building(s).world.segments() for s in (0, 1, 2)]
    for i in range(3):
        for j in range(i + 1, 3):
            assert segs[i].shape != segs[j].shape or not np.allclose(segs[i], segs[j])
    # even with type, layout and size fixed, the seed changes the building
    p = BuildingParams(building_type="office", layout="straight", width=14, height=23)
    a, b = generate_building(1, p), generate_building(2, p)
    assert (a.width, a.height) == (b.width, b.height) == (14.0, 23.0)
    assert a.world.segments().shape != b.world.segments().shape or not np.allclose(
        a.world.segments(), b.world.segments()
    )


# ------------------------------------------------------------------ the corpus
def test_every_type_and_layout_appears_over_the_tuning_seeds() -> None:
    types = {building(s).building_type for s in TUNING}
    layouts = {building(s).layout for s in TUNING}
    assert types == set(BUILDING_TYPES)
    assert layouts == set(LAYOUTS)
    # resolve_params predicts what generate_building builds, without building it
    for s in (0, 7, 13):
        p = resolve_params(s)
        b = building(s)
        assert (p.building_type, p.layout, p.width, p.height) == (
            b.building_type,
            b.layout,
            b.width,
            b.height,
        )


def test_sizes_lie_between_10x10_and_40x60() -> None:
    sides = np.array([sorted((building(s).width, building(s).height)) for s in TUNING])
    assert sides.min() >= 10.0 and sides[:, 0].max() <= 40.0 and sides[:, 1].max() <= 60.0
    assert sides[:, 1].max() > 35.0 and sides[:, 0].min() < 16.0  # the corpus spans sizes
    for s in (3, 20):  # the outer walls' outer faces are the footprint
        b = building(s)
        assert b.world.bounds == pytest.approx((0.0, 0.0, b.width, b.height))


def test_every_room_is_reachable_through_a_door() -> None:
    """Exact check with shapely: the free space shrunk by 0.3 m (a robot's radius) has one
    component reaching the corridors, and it covers nearly all of every room."""
    for s in TUNING:
        b = building(s)
        core = b.world.free_space.buffer(-0.3)
        start = Point(*b.shell.graph[0][0])
        main = next(g for g in shapely.get_parts(core) if g.distance(start) < 1e-9)
        for room in b.rooms:
            inner = room.inner.poly()
            total = core.intersection(inner).area
            assert main.intersection(inner).area >= 0.95 * total > 0.0, (s, room.index)
        assert b.unreachable_rooms() == []
        for room in b.rooms:  # and every room has a door
            assert room.doors or any(d.other == room.index for d in b.doors)


def test_doors_and_walls_stay_within_their_ranges() -> None:
    widths, thick = [], []
    for s in TUNING:
        b = building(s)
        widths += [d.width for d in b.doors]
        thick += [d.thickness for d in b.doors] + [b.shell.t_out]
    assert 0.8 - 1e-9 <= min(widths) < 0.9 and 1.7 < max(widths) <= 1.8 + 1e-9
    assert 0.1 - 1e-9 <= min(thick) < 0.12 and 0.28 < max(thick) <= 0.3 + 1e-9
    # a door really is a gap: its centre is free, both jambs are walls
    b = building(4)
    w = _walls(b)
    for d in b.doors[:20]:
        along = np.array([1.0, 0.0]) if d.axis == 0 else np.array([0.0, 1.0])
        assert not w.contains(Point(*d.center))
        for side in (-1, 1):
            assert w.distance(Point(*(d.center + side * along * (d.width / 2 + 0.05)))) < 1e-9


def test_furniture_of_every_kind_at_the_office_density() -> None:
    dens = []
    for s in TUNING:
        b = building(s)
        items = {it.item for it in b.items}
        assert set(MUST_HAVE) <= items, (s, set(MUST_HAVE) - items)
        kinds = {o.kind for o in b.world.obstacles}
        assert {"wall", "furniture", "circle", "irregular", "blob", "complex"} <= kinds
        walls = _walls(b)
        for it in b.items:
            if it.item == "column":  # round column 0.3-0.5 m from a wall
                assert 0.3 - 1e-6 <= walls.distance(it.parts[0]) <= 0.5 + 1e-6
            if it.item in ("couch", "counter"):  # L-shaped: non-convex
                assert it.parts[0].convex_hull.area > it.parts[0].area * 1.05
            if it.item == "table_chairs":
                assert len(it.parts) >= 3  # a table and >= 2 chairs
        dens.append(b.clutter)
    assert np.mean(dens) == pytest.approx(OFFICE_CLUTTER, abs=0.005)
    assert min(dens) > 0.07


def test_clutter_is_a_parameter() -> None:
    empty = generate_building(5, BuildingParams(clutter=0.0))
    dense = generate_building(5, BuildingParams(clutter=0.15))
    assert empty.items == [] and {o.kind for o in empty.world.obstacles} == {"wall"}
    assert dense.clutter > 0.13 > building(5).clutter
    # the shell does not depend on the clutter
    walls_only = building(5).metric_map().polylines[: len(empty.metric_map().polylines)]
    for a, c in zip(empty.metric_map().polylines, walls_only, strict=True):
        np.testing.assert_array_equal(a, c)


def test_params_are_respected_and_validated() -> None:
    p = BuildingParams(building_type="lab", layout="ring", width=24.0, height=30.0, people=0)
    b = generate_building(3, p)
    assert (b.building_type, b.layout, b.width, b.height) == ("lab", "ring", 24.0, 30.0)
    assert generate_building(3, BuildingParams(width=12.0)).width == 12.0
    with pytest.raises(InvalidWorld, match="ring layout needs a short side"):
        generate_building(0, BuildingParams(layout="ring", width=10.0, height=10.0))
    with pytest.raises(ValidationError):
        BuildingParams(width=9.0)
    with pytest.raises(ValidationError, match="short side"):
        BuildingParams(width=45.0, height=50.0)
    with pytest.raises(ValidationError, match="door_width"):
        BuildingParams(door_width=(1.5, 1.0))
    with pytest.raises(ValidationError):
        BuildingParams(layout="spiral")


def test_wall_details_are_optional() -> None:
    plain = generate_building(7, BuildingParams(wall_details=False))
    assert plain.shell.details == [] and building(7).shell.details
    kinds = {d.kind for s in TUNING for d in building(s).shell.details}
    assert kinds == {"pilaster", "niche", "column"}


# ------------------------------------------------------------------ maps
def test_metric_map_is_every_obstacle_ring() -> None:
    b = building(2)
    m = b.metric_map()
    assert m.kind == "metric" and len(m.polylines) == len(b.world.rings())
    assert m.segments().shape == b.world.segments().shape


def test_schematic_outlines_lie_on_inner_wall_faces_and_hold_no_furniture() -> None:
    for s in (0, 4, 9, 12):
        b = building(s)
        sm = b.schematic()
        assert sm.map_data.kind == "schematic"
        faces = shapely.boundary(b.shell.walls(SchematicParams().detail_min_size))
        outer = box(0, 0, b.width, b.height).exterior
        furn = shapely.union_all(_furniture(b))
        for p in sm.clean:
            line = shapely.linestrings(p)
            assert faces.distance(shapely.points(p)).max() < 1e-9  # on wall faces
            assert shapely.hausdorff_distance(line, faces.intersection(line.buffer(1e-7))) < 1e-6
            assert outer.distance(line) > 0.15  # the building's outline is not drawn
            assert not line.intersects(furn)  # no furniture outline, nothing across furniture
        for p in sm.map_data.polylines:  # jittered: still no polyline inside a furniture piece
            assert not furn.contains(shapely.linestrings(p))
    # furniture plays no part: the same building without furniture has the same schematic
    a = generate_building(9, BuildingParams(clutter=0.0)).schematic()
    for pa, pb in zip(
        a.map_data.polylines, building(9).schematic().map_data.polylines, strict=True
    ):
        np.testing.assert_array_equal(pa, pb)


def test_schematic_corner_jitter_and_scale_error_stay_within_bounds() -> None:
    scales = []
    for s in range(12):
        sm = building(s).schematic()
        d = np.concatenate(
            [np.hypot(*(u - c).T) for u, c in zip(sm.unscaled(), sm.clean, strict=True)]
        )
        assert d.min() >= 0.02 - 1e-9 and d.max() <= 0.10 + 1e-9
        scales.append(sm.scale - 1.0)
    assert max(abs(v) for v in scales) <= 0.02 and np.std(scales) > 0.005
    b = building(7)
    sm = b.schematic(SchematicParams(scale_error=0.015, corner_jitter=(0.05, 0.05)))
    c = sm.center
    clean = np.vstack(sm.clean) - c
    got = np.vstack(sm.map_data.polylines) - c
    fitted = float(np.sum(clean * got) / np.sum(clean * clean))  # least-squares scale
    assert fitted == pytest.approx(1.015, abs=0.001)
    d = np.concatenate([np.hypot(*(u - q).T) for u, q in zip(sm.unscaled(), sm.clean, strict=True)])
    np.testing.assert_allclose(d, 0.05, atol=1e-9)


def test_schematic_drops_wall_details_below_the_size() -> None:
    b = next(building(s) for s in TUNING if any(d.size >= 0.2 for d in building(s).shell.details))
    keep_all = b.schematic(SchematicParams(detail_min_size=0.0))
    drop_all = b.schematic(SchematicParams(detail_min_size=10.0))
    default = b.schematic()
    assert keep_all.details_kept == len(b.shell.details) and drop_all.details_kept == 0
    assert 0 < default.details_kept < len(b.shell.details)
    plain = shapely.boundary(b.shell.walls(min_detail=10.0))
    full = shapely.boundary(b.shell.walls(min_detail=0.0))
    for p in drop_all.clean:
        assert plain.distance(shapely.points(p)).max() < 1e-9
    off = max(plain.distance(shapely.points(p)).max() for p in keep_all.clean)
    assert off > 0.05  # kept details bend the outline off the plain wall faces
    for p in keep_all.clean:
        assert full.distance(shapely.points(p)).max() < 1e-9


def test_schematic_door_gaps_open_or_closed() -> None:
    b = building(1)
    is_open = b.schematic(SchematicParams(closed_doors=0.0))
    closed = b.schematic(SchematicParams(closed_doors=1.0))
    half = b.schematic(SchematicParams(closed_doors=0.5))
    assert is_open.closed_doors == () and len(closed.closed_doors) == len(b.doors)
    assert 0 < len(half.closed_doors) < len(b.doors)
    lines_open = shapely.union_all([shapely.linestrings(p) for p in is_open.clean])
    lines_closed = shapely.union_all([shapely.linestrings(p) for p in closed.clean])
    for d in b.doors:
        inside = d.gap(0.0).buffer(-0.02)  # the gap without its jambs
        assert not lines_open.intersects(inside)
        across = lines_closed.intersection(d.gap(0.0).buffer(1e-6))
        assert across.length == pytest.approx(d.width, abs=1e-6)
