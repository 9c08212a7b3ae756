"""Tours through generated buildings and their two setups: clearance, the seed's statistics,
scan budgets, odometry, and moving people seen by the laser at the right time."""

from __future__ import annotations

from functools import cache

import numpy as np
import pytest

from service.errors import InvalidMessage
from sim_publisher.generator import Building, BuildingParams, SchematicParams, generate_building
from sim_publisher.generator.layout import DOOR_APPROACH
from sim_publisher.generator.tours import RoomPlanners, door_inside_point, room_loop, tour_doors
from sim_publisher.scenario import building_setup
from sim_publisher.trajectory import OdometryNoise, relative_motion, run_stats

SEEDS = (0, 2, 4, 9, 11, 12, 14, 19)  # every layout and type among them


@cache
def building(seed: int, people: int = 0) -> Building:
    return generate_building(seed, BuildingParams(people=people))


def test_the_sample_covers_every_layout_and_type() -> None:
    assert {building(s).layout for s in SEEDS} == {"straight", "L", "ring", "atrium"}
    assert {building(s).building_type for s in SEEDS} == {"office", "lab", "hospital"}


@pytest.mark.parametrize("seed", SEEDS)
def test_tour_keeps_its_clearance_from_every_obstacle(seed: int) -> None:
    b = building(seed)
    xy = np.asarray(b.tour.xy[::2])  # every 4 mm
    c = b.world.clearance(xy)
    assert c.min() >= b.params.tour_clearance
    assert np.all(b.world.is_free(xy, b.params.tour_clearance - 1e-9))


@pytest.mark.parametrize("seed", SEEDS)
def test_tour_runs_through_corridors_into_several_rooms(seed: int) -> None:
    b = building(seed)
    assert b.tour.length == pytest.approx(b.params.tour_length, abs=0.01)
    assert len(b.visits) >= 2 and len(set(b.visits)) == len(b.visits)
    xy = np.asarray(b.tour.xy)
    in_room = np.zeros(len(xy), bool)
    for k in b.visits:
        r = b.rooms[k].rect
        inside = (xy[:, 0] > r.x0) & (xy[:, 0] < r.x1) & (xy[:, 1] > r.y0) & (xy[:, 1] < r.y1)
        assert inside.sum() > 100, (seed, k)  # the tour really enters each visited room
        in_room |= inside
    assert in_room[0]  # it starts inside a room
    assert (~in_room).mean() > 0.1  # and spends part of its way in corridors / the hall
    # through doors squarely: wherever it crosses a door's wall line, it is near its centre
    for d in b.doors:
        n = d.normal
        off = (xy - d.center) @ n
        lateral = np.abs((xy - d.center) @ np.array([-n[1], n[0]]))
        near = (np.abs(off) < d.thickness / 2) & (lateral < d.width / 2 + 0.1)
        if near.any():
            assert lateral[near].max() < d.width / 2 - b.params.tour_clearance + 0.02


@pytest.mark.parametrize("seed", SEEDS)
def test_setups_reproduce_the_seed_statistics_and_scan_budget(seed: int) -> None:
    b = building(seed)
    s1, s2 = building_setup(b, 1, max_scans=None), building_setup(b, 2)
    st1, st2 = run_stats(s1.truth), run_stats(s2.truth)
    assert st1["mean_step_mm"] == pytest.approx(11.0, rel=0.15)
    assert st1["mean_rotation_deg"] == pytest.approx(4.0, rel=0.15)
    assert st2["mean_step_mm"] == pytest.approx(104.0, rel=0.15)
    assert st2["mean_rotation_deg"] == pytest.approx(31.0, rel=0.15)
    assert len(s1) <= 2500 and len(s2) <= 250
    assert s1.map_data.kind == "metric" and s2.map_data.kind == "schematic"
    assert (s1.proximity_mm, s2.proximity_mm, s1.proximity_deg) == (100.0, 500.0, 45.0)
    # the same continuous trajectory: setup-2 positions lie on setup-1's (within 6 mm)
    d = np.hypot(*(s2.truth[:, None, :2] - s1.truth[None, :, :2]).transpose(2, 0, 1)).min(1)
    assert d.max() < 0.006


def test_tour_length_is_a_parameter_capped_by_the_building() -> None:
    short = generate_building(2, BuildingParams(tour_length=8.0))
    assert short.tour.length == pytest.approx(8.0, abs=0.01)
    assert len(building_setup(short, 2)) == pytest.approx(8.0 / 0.104, abs=2)
    tiny = generate_building(0, BuildingParams(width=10, height=10, tour_length=400.0))
    assert tiny.tour.length < 400.0  # visits every room it can, then stops
    usable = tour_doors(tiny.shell, 2 * tiny.params.tour_clearance + 0.06)
    planners = RoomPlanners(tiny.shell, tiny.world.union)
    rng = np.random.default_rng(0)
    can = {r for r, d in usable.items() if room_loop(planners.get(r), door_inside_point(d, r), rng)}
    assert len(can) >= 3 and set(tiny.visits) == can


def test_setup_scans_see_the_true_world_and_carry_odometry() -> None:
    b = building(4)
    s = building_setup(b, 2, seed=3, max_scans=40)
    assert len(s) == 40 and s.odom.shape == (40, 3)
    np.testing.assert_array_equal(s.odom[0], s.truth[0])
    r, a = s.scan(10)
    r2, _ = building_setup(b, 2, seed=3, max_scans=40).scan(10)
    np.testing.assert_array_equal(r, r2)
    assert r.shape == a.shape == (361,) and np.isfinite(r).mean() > 0.9
    exact = s.laser.exact(s.truth[10])
    ok = np.isfinite(r)
    assert np.median(np.abs(r[ok] - exact[ok])) < 0.02
    # odometry: seeded, drifting, step increments close to the truth
    full = building_setup(b, 2, seed=3)
    other = building_setup(b, 2, seed=4)
    assert not np.array_equal(full.odom, other.odom)
    err = np.hypot(*(full.odom - full.truth)[:, :2].T)
    assert err[-1] > 0.05
    dr = relative_motion(full.odom[:-1], full.odom[1:]) - relative_motion(
        full.truth[:-1], full.truth[1:]
    )
    assert np.median(np.abs(dr[:, 0])) < 0.01 and np.median(np.abs(dr[:, 2])) < np.deg2rad(1)
    exact_odom = building_setup(b, 2, seed=3, odometry=OdometryNoise(0.0, 0.0, 0.0, 0.0, 0.0)).odom
    np.testing.assert_allclose(exact_odom, full.truth, atol=1e-9)
    with pytest.raises(InvalidMessage, match="setup must be 1 or 2"):
        building_setup(b, 3)
    with pytest.raises(IndexError):
        s.scan(40)


def test_setup2_judges_poses_on_the_schematic_map_with_its_scale_error() -> None:
    b = building(4)
    params = SchematicParams(scale_error=0.02)
    s = building_setup(b, 2, seed=3, max_scans=60, schematic=params)
    plan = b.schematic(params)
    want = s.truth.copy()
    want[:, :2] = plan.center + 1.02 * (s.truth[:, :2] - plan.center)
    np.testing.assert_allclose(s.reference, want, atol=1e-12)
    # the proximity test follows the map frame: a pose 0.45 m from the map-frame truth,
    # away from the world truth, passes although it is > 0.5 m from the world truth
    off = s.reference[:, :2] - s.truth[:, :2]
    i = int(np.argmax(np.hypot(*off.T)))
    assert np.hypot(*off[i]) > 0.1
    pose = s.reference[i].copy()
    pose[:2] += 0.45 * off[i] / np.hypot(*off[i])
    assert np.hypot(*(pose - s.truth[i])[:2]) > 0.5
    assert s.passed(i, pose) and s.passed(i, s.reference[i])
    assert not s.passed(i, s.reference[i] + np.array([0.0, 0.6, 0.0]))
    # setup 1's map is the world itself
    s1 = building_setup(b, 1, seed=3, max_scans=20)
    assert s1.map_truth is None and s1.reference is s1.truth


def test_moving_people_show_up_in_scans_at_the_right_time() -> None:
    b = building(9, people=4)
    assert len(b.people) == 4
    for p in b.people:  # people-sized, walking between rooms, clear of static obstacles
        assert 0.2 <= p.radius <= 0.3 and 0.5 <= p.speed <= 1.3
        assert b.world.clearance(p.path).min() >= p.radius
    s = building_setup(b, 2)
    seen = 0
    for i in range(len(s)):
        circles = s.circles(i)
        np.testing.assert_allclose(circles, b.people_at(float(s.times[i])))
        static = s.laser.exact(s.truth[i])
        dyn = s.laser.exact(s.truth[i], circles)
        changed = np.flatnonzero(
            ~np.isclose(np.nan_to_num(dyn, nan=-1), np.nan_to_num(static, nan=-1))
        )
        if changed.size == 0:
            continue
        seen += 1
        # each changed beam ends on a person's circle at this scan's time ...
        x, y, th = s.truth[i]
        ang = s.laser.angles[changed] + th
        hit = np.c_[x + dyn[changed] * np.cos(ang), y + dyn[changed] * np.sin(ang)]
        gap = np.hypot(*(hit[:, None, :] - circles[None, :, :2]).transpose(2, 0, 1)) - circles[:, 2]
        assert np.abs(gap).min(axis=1).max() < 1e-9
        assert np.all(dyn[changed] <= np.nan_to_num(static[changed], nan=np.inf))
        # ... and the noisy scan sees it too (noise draws do not depend on the people)
        r, _ = s.scan(i)
        ok = np.isfinite(r[changed])
        assert np.median(np.abs(r[changed][ok] - dyn[changed][ok])) < 0.03
    assert seen > 10
    # a person is where their path says at time t, and elsewhere at another time
    p = b.people[0]
    L = float(p.s[-1])
    t_mid = ((L / 2 - p.phase) % (2 * L)) / p.speed  # at half the path, walking out
    mid = [np.interp(L / 2, p.s, p.path[:, 0]), np.interp(L / 2, p.s, p.path[:, 1])]
    np.testing.assert_allclose(p.position(t_mid), mid, atol=1e-9)
    np.testing.assert_allclose(p.position(t_mid + 2 * L / p.speed), mid, atol=1e-9)  # period
    assert np.hypot(*(p.position(t_mid) - p.position(t_mid + 3.0))) > 1.0
    # without people (or with people=False) the scans are the static ones
    quiet = building_setup(b, 2, people=False)
    np.testing.assert_array_equal(quiet.scan(5)[0], building_setup(building(9), 2).scan(5)[0])


def test_people_keep_clear_of_the_robot() -> None:
    b = building(9, people=4)
    s = building_setup(b, 1)
    gaps = [
        np.min(np.hypot(*(s.circles(i)[:, :2] - s.truth[i, :2]).T) - s.circles(i)[:, 2])
        for i in range(0, len(s), 3)
    ]
    assert min(gaps) >= 0.3 - 1e-9


def test_door_approaches_are_free_of_furniture() -> None:
    for seed in SEEDS[:4]:
        b = building(seed)
        furn = [o.geometry for o in b.world.obstacles if o.kind != "wall"]
        for d in b.doors:
            ap = d.approach()
            assert not any(f.intersects(ap) for f in furn), (seed, d.index)
            depth = ap.bounds[3] - ap.bounds[1] if d.axis == 0 else ap.bounds[2] - ap.bounds[0]
            assert depth == pytest.approx(2 * DOOR_APPROACH)
