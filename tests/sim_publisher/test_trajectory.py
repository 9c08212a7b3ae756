"""The office tour and the two setups: statistics vs the paper, clearance, odometry."""

from __future__ import annotations

import numpy as np
import pytest

from service.errors import InvalidMessage
from sim_publisher.office import office_world
from sim_publisher.scenario import make_setup, run_stats
from sim_publisher.trajectory import relative_motion, simulate_odometry, tour_poses

PAPER = {1: (43.03, 11.0, 4.0), 2: (43.03, 104.0, 30.6)}


@pytest.mark.parametrize("setup", [1, 2])
def test_tour_statistics_within_ten_percent_of_the_paper(setup: int) -> None:
    s = make_setup(setup)
    st = run_stats(s.truth)
    length, step_mm, rot_deg = PAPER[setup]
    assert st["path_length_m"] == pytest.approx(length, rel=0.10)
    assert st["mean_step_mm"] == pytest.approx(step_mm, rel=0.10)
    assert st["mean_rotation_deg"] == pytest.approx(rot_deg, rel=0.10)
    assert len(s) == pytest.approx(length * 1000 / step_mm, rel=0.10)


def test_both_setups_sample_the_same_route() -> None:
    a, b = make_setup(1), make_setup(2)
    assert a.map_data.kind == "metric" and b.map_data.kind == "schematic"
    assert (a.proximity_mm, b.proximity_mm, a.proximity_deg) == (100.0, 500.0, 45.0)
    # every setup-2 position lies within 6 mm (half a setup-1 step) of a setup-1 position
    diff = b.truth[:, None, :2] - a.truth[None, :, :2]
    d = np.hypot(diff[..., 0], diff[..., 1]).min(axis=1)
    assert d.max() < 0.006


def test_tour_keeps_clearance_from_every_obstacle() -> None:
    w = office_world()
    dense = tour_poses(0.005)
    c = w.clearance(dense[:, :2])
    assert c.min() >= 0.15
    assert np.all(w.is_free(dense[:, :2], 0.15))
    # passes through the corridor and ends in the top-left room near the pillar
    assert np.any((dense[:, 0] > 5.7) & (dense[:, 0] < 7.5) & (dense[:, 1] > 15.0))
    assert dense[-1, 0] < 5.5 and dense[-1, 1] > 17.0


def test_heading_oscillates_around_the_direction_of_travel() -> None:
    t = tour_poses(0.011)
    motion = np.diff(t[:, :2], axis=0)
    travel = np.arctan2(motion[:, 1], motion[:, 0])
    off = np.angle(np.exp(1j * (t[:-1, 2] - travel)))
    assert abs(np.mean(off)) < np.deg2rad(3)
    assert np.deg2rad(20) < np.max(np.abs(off)) < np.deg2rad(40)


def test_odometry_is_seeded_and_drifts_realistically() -> None:
    truth = tour_poses(0.104)
    a = simulate_odometry(truth, seed=3)
    np.testing.assert_array_equal(a, simulate_odometry(truth, seed=3))
    assert not np.array_equal(a, simulate_odometry(truth, seed=4))
    np.testing.assert_array_equal(a[0], truth[0])
    err = np.hypot(*(a - truth)[:, :2].T)
    assert 0.01 < err[40] < 1.0  # ~4 m travelled: centimetres to decimetres
    assert err[-1] > 0.5  # drift accumulates over 43 m
    # per-step increments stay close to the truth (what baselines use to seed)
    dr = relative_motion(a[:-1], a[1:]) - relative_motion(truth[:-1], truth[1:])
    assert np.median(np.abs(dr[:, 0])) < 0.01 and np.median(np.abs(dr[:, 2])) < np.deg2rad(1)


def test_setup_scans_are_deterministic_and_truncation_works() -> None:
    s = make_setup(2, seed=1, max_scans=5)
    assert len(s) == 5 and s.odom.shape == (5, 3)
    r1, a1 = s.scan(3)
    r2, _ = make_setup(2, seed=1, max_scans=5).scan(3)
    np.testing.assert_array_equal(r1, r2)
    assert r1.shape == a1.shape == (361,)
    assert np.mean(np.isfinite(r1)) > 0.9
    # the scan sees the true world: exact ranges agree with the noisy ones to ~noise level
    exact = s.laser.exact(s.truth[3])
    ok = np.isfinite(r1)
    assert np.median(np.abs(r1[ok] - exact[ok])) < 0.02
    with pytest.raises(IndexError):
        s.scan(5)
    with pytest.raises(InvalidMessage, match="setup must be 1 or 2"):
        make_setup(3)
    with pytest.raises(InvalidMessage, match="max_scans"):
        make_setup(1, max_scans=0)


def test_passed_is_the_paper_proximity_test() -> None:
    s = make_setup(1, max_scans=3)
    t = s.truth[1].copy()
    assert s.passed(1, t + np.array([0.07, 0.07, np.deg2rad(44)]))
    assert not s.passed(1, t + np.array([0.08, 0.07, 0.0]))
    assert not s.passed(1, t + np.array([0.0, 0.0, np.deg2rad(46)]))


def test_tour_class_reproduces_the_office_tour() -> None:
    from sim_publisher.trajectory import TOUR_WAYPOINTS, Tour, office_tour

    t = Tour.from_control_points(TOUR_WAYPOINTS, 6)
    np.testing.assert_array_equal(t.poses(0.011), tour_poses(0.011))
    np.testing.assert_array_equal(office_tour().poses(0.104, 7), tour_poses(0.104, 7))
    cut = t.truncated(10.0)
    assert cut.length == pytest.approx(10.0, abs=0.003)
    np.testing.assert_array_equal(cut.poses(0.104), t.poses(0.104)[: len(cut.poses(0.104))])


@pytest.mark.parametrize("which", ["office", "zigzag"])
def test_calibration_hits_both_turn_statistics(which: str) -> None:
    from sim_publisher.trajectory import Tour, office_tour

    if which == "office":
        tour = office_tour()
    else:  # many corners: the tangent alone turns a lot
        pts = np.array([[0.0, 0.0], [2, 1], [4, 0], [6, 1], [8, 0], [8, 3], [5, 4], [2, 3]])
        tour = Tour.from_control_points(pts, 6)
    cal = tour.calibrated()
    s1, s2 = run_stats(cal.poses(0.011)), run_stats(cal.poses(0.104))
    assert s1["mean_rotation_deg"] == pytest.approx(4.0, rel=0.02)
    assert s2["mean_rotation_deg"] == pytest.approx(30.6, rel=0.02)
    np.testing.assert_array_equal(cal.xy, tour.xy)  # only the heading changes
