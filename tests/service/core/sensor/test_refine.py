"""The map model and the precise fit (service/core/sensor/mapmodel.py,
service/core/sensor/refine.py)."""

from __future__ import annotations

import itertools
from collections.abc import Callable

import numpy as np
import pytest

from service.core import kernels
from service.core.pose import invert, transform_points
from service.core.sensor.mapmodel import MapModel
from service.core.sensor.refine import RefineParams, refine_pose, scan_normals
from service.core.types import MapData

ROOM = MapData.from_lists(
    "room", "metric", [[[0, 0], [6, 0], [6, 4], [0, 4], [0, 0]], [[2, 1.5], [3, 1.5], [3, 2.2]]]
)


def _scan_of(pose: np.ndarray, rng: np.random.Generator, n: int = 300) -> np.ndarray:
    """Points sampled on the room's walls that a robot at ``pose`` sees, robot frame."""
    pts = []
    for p in ROOM.polylines:
        for a, b in itertools.pairwise(p):
            t = rng.uniform(0, 1, n // 5)
            pts.append(a + t[:, None] * (b - a))
    world = np.vstack(pts) + rng.normal(0, 0.005, (sum(len(q) for q in pts), 2))
    return transform_points(invert(pose), world)


def test_nearest_finds_the_segment_and_respects_the_normal_gate() -> None:
    m = MapModel(ROOM)
    q = np.array([[1.0, 0.05], [5.9, 2.0], [20.0, 20.0]])
    got = m.nearest(q, 0.5)
    assert got.segment[2] == -1 and np.isinf(got.distance[2])
    np.testing.assert_allclose(got.distance[:2], [0.05, 0.1], atol=1e-12)
    np.testing.assert_allclose(got.foot[0], [1.0, 0.0], atol=1e-12)
    # a point whose surface normal lies along the wall may not use that wall
    gated = m.nearest(q[:1], 0.5, point_normals=np.array([[1.0, 0.0]]), max_angle=0.5)
    assert gated.segment[0] == -1


@pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba kernels not installed")
def test_nearest_kernel_agrees_with_the_numpy_reference(monkeypatch: pytest.MonkeyPatch) -> None:
    m = MapModel(ROOM)
    q = np.random.default_rng(3).uniform(-1, 7, (500, 2))
    a = m.nearest(q, 0.9)
    monkeypatch.setattr(kernels, "HAVE_NUMBA", False)
    b = m.nearest(q, 0.9)
    np.testing.assert_array_equal(a.segment, b.segment)
    np.testing.assert_allclose(a.distance, b.distance, atol=1e-12)


@pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba kernels not installed")
def test_scan_normals_kernel_agrees_with_the_numpy_reference(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    rng = np.random.default_rng(5)
    pts = np.cumsum(rng.normal(0.0, 0.08, (400, 2)), axis=0) + np.array([3.0, 0.0])
    pts[rng.random(400) < 0.05] += 2.0  # isolated points: no neighbour within the gap
    starts = np.array([0, 17, 18, 150, 399, 400])  # the ends and a one-point polyline too
    a = scan_normals(pts, starts=starts)
    monkeypatch.setattr(kernels, "HAVE_NUMBA", False)
    b = scan_normals(pts, starts=starts)
    np.testing.assert_array_equal(a, b)
    assert 0 < np.isnan(b[:, 0]).sum() < 100


def test_refine_recovers_a_displaced_pose_to_millimetres() -> None:
    rng = np.random.default_rng(7)
    truth = np.array([2.5, 2.8, 0.4])
    pts = _scan_of(truth, rng)
    start = truth + np.array([0.12, -0.09, 0.06])
    r = refine_pose(MapModel(ROOM), pts, start, RefineParams())
    assert np.hypot(*(r.pose[:2] - truth[:2])) < 0.003
    assert abs(r.pose[2] - truth[2]) < 0.002
    assert r.inlier_fraction > 0.95
    assert r.fit.covariance is not None and np.all(np.diag(r.fit.covariance) > 0)


def test_the_prior_holds_the_direction_a_corridor_leaves_open() -> None:
    """Two parallel walls: the scan fixes y and theta, not x; the prior decides x."""
    corridor = MapData.from_lists("c", "metric", [[[-50, 0], [50, 0]], [[-50, 2], [50, 2]]])
    rng = np.random.default_rng(1)
    x = rng.uniform(-5, 5, 200)
    world = np.column_stack([x, np.where(rng.random(200) < 0.5, 0.0, 2.0)])
    truth = np.array([0.0, 1.0, 0.0])
    pts = transform_points(invert(truth), world)
    prior = np.array([0.3, 1.05, 0.02])
    info = np.diag([1 / 0.1**2, 1 / 0.1**2, 1 / 0.05**2])
    r = refine_pose(
        MapModel(corridor), pts, prior, RefineParams(), prior=prior, prior_information=info
    )
    assert abs(r.pose[1] - 1.0) < 0.003 and abs(r.pose[2]) < 0.002
    assert r.pose[0] == pytest.approx(0.3, abs=0.01)  # x stays at the prior's


def test_loglik_prefers_the_true_pose_and_weights_discount_points() -> None:
    rng = np.random.default_rng(11)
    truth = np.array([3.0, 2.0, -0.2])
    pts = _scan_of(truth, rng)
    m = MapModel(ROOM)
    good = refine_pose(m, pts, truth, RefineParams(iterations=1))
    bad = refine_pose(m, pts, truth + np.array([0.0, 0.0, 0.5]), RefineParams(iterations=1))
    assert good.loglik > bad.loglik
    w = np.ones(len(pts))
    assert good.weighted_loglik(w, RefineParams()) == pytest.approx(good.loglik)


def test_effective_points_let_the_prior_weigh_against_many_correlated_points() -> None:
    """With every point counted, 300 points outweigh a prior 5 cm off; counted as 20
    independent returns the prior pulls the fit part of the way; the prior's own weight is
    unchanged when there are fewer points than that."""
    rng = np.random.default_rng(8)
    truth = np.array([2.5, 2.8, 0.4])
    pts = _scan_of(truth, rng)
    prior = truth + np.array([0.05, 0.0, 0.0])
    info = np.diag([1.0 / 0.02**2, 1.0 / 0.02**2, 1.0 / 0.01**2])
    m = MapModel(ROOM)
    full = refine_pose(m, pts, prior, RefineParams(), prior=prior, prior_information=info)
    eff = RefineParams(effective_points=20.0)
    few = refine_pose(m, pts, prior, eff, prior=prior, prior_information=info)
    off_full = float(np.hypot(*(full.pose[:2] - truth[:2])))
    off_few = float(np.hypot(*(few.pose[:2] - truth[:2])))
    assert off_full < 0.01
    assert off_few > 2.0 * off_full and off_few < 0.05
    sub = pts[:15]
    a = refine_pose(m, sub, prior, RefineParams(), prior=prior, prior_information=info)
    b = refine_pose(m, sub, prior, eff, prior=prior, prior_information=info)
    np.testing.assert_allclose(a.pose, b.pose, atol=1e-12)


def test_scan_normals_of_stacked_polylines_are_each_polylines_own(real_scene: Callable) -> None:
    """Normals of a scan's polylines stacked with their starts given are, bit for bit, the
    normals of each polyline alone (no neighbour is taken across a polyline's end), including
    polylines of one and two points."""
    sc = real_scene(2, 30)
    parts = [f.points for f in sc.P.features]
    parts += [parts[0][:1], parts[1][:2], parts[2][::40]]  # short ones, and sparse points
    stacked = np.vstack(parts)
    starts = np.cumsum([len(p) for p in parts])[:-1]
    got = scan_normals(stacked, starts=starts)
    want = np.vstack([scan_normals(p) for p in parts])
    assert np.array_equal(got, want, equal_nan=True)
    assert np.isnan(got[starts[-3]]).all()  # the lone point has no normal
    # without the starts the ends of neighbouring polylines would pair up
    assert not np.array_equal(scan_normals(stacked), want, equal_nan=True)
