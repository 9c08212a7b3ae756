"""Discrete curve evolution and the relevance measure (paper §4.1, eq. 2). Runs in < 1 s."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest

from service.core import kernels
from service.core.sensor.raycast import RayCaster
from service.core.shapes.dce import (
    DCE_NOISE_THRESHOLD,
    CurveEvolution,
    dce,
    refine_vertices,
    relevance,
    relevance_array,
)
from service.errors import LocalizationError


def room_scan(width: float, height: float, cx: float, cy: float, n: int, sigma: float, seed: int):
    """A 360-degree scan from (cx, cy) inside a width x height rectangle, radial noise."""
    rng = np.random.default_rng(seed)
    a = -math.pi + (np.arange(n) + 0.5) * 2 * math.pi / n
    c, s = np.cos(a), np.sin(a)
    with np.errstate(divide="ignore"):
        tx = np.where(c > 0, (width - cx) / c, np.where(c < 0, -cx / c, np.inf))
        ty = np.where(s > 0, (height - cy) / s, np.where(s < 0, -cy / s, np.inf))
    r = np.minimum(tx, ty) + rng.normal(0.0, sigma, n)
    corners = np.array(
        [[width - cx, height - cy], [-cx, height - cy], [-cx, -cy], [width - cx, -cy]]
    )
    return np.column_stack((r * c, r * s)), corners


def test_relevance_of_collinear_triple_is_zero() -> None:
    assert relevance((0.0, 0.0), (1.0, 1.0), (3.0, 3.0)) == pytest.approx(0.0, abs=1e-15)


def test_relevance_of_right_angle_matches_hand_value() -> None:
    # 1 + 1 - sqrt(2)
    assert relevance((0.0, 1.0), (0.0, 0.0), (1.0, 0.0)) == pytest.approx(2 - math.sqrt(2))
    # arms 3 and 4: 3 + 4 - 5
    assert relevance((0.0, 3.0), (0.0, 0.0), (4.0, 0.0)) == pytest.approx(2.0)


def test_relevance_array_matches_scalar() -> None:
    rng = np.random.default_rng(0)
    p = rng.normal(size=(20, 2))
    ra = relevance_array(p)
    assert ra.shape == (18,)
    for i in range(18):
        assert ra[i] == pytest.approx(relevance(tuple(p[i]), tuple(p[i + 1]), tuple(p[i + 2])))
    assert relevance_array(p[:2]).shape == (0,)


def test_dce_keeps_the_four_corners_of_a_noisy_rectangle() -> None:
    # 4 m x 3 m room, 400 beams, 1 cm range noise; the scan polyline starts and ends mid-wall
    # so the four room corners are interior vertices.
    exact = 0
    for seed in range(10):
        pts, corners = room_scan(4.0, 3.0, 1.7, 1.2, 400, 0.01, seed)
        keep = dce(pts)
        assert keep[0] == 0 and keep[-1] == 399
        kept = pts[keep]
        for c in corners:  # a kept vertex at every corner (beams there are 4-5 cm apart)
            assert np.min(np.hypot(*(kept - c).T)) < 0.06
        assert len(keep) <= 8  # the 4 corners, 2 ends and at most one noise pair
        exact += len(keep) == 6
    # noise vertices are dropped: measured 9 of 10 exact (seed 1 keeps one back-step pair of
    # adjacent beams, whose relevance is ~2x the 2 cm step; the second DCE stage removes it)
    assert exact >= 9


def test_dce_on_noisy_straight_wall_leaves_its_ends() -> None:
    rng = np.random.default_rng(5)
    x = np.linspace(0.0, 3.0, 200)
    pts = np.column_stack((x, 2.0 + rng.normal(0, 0.005, x.size)))
    assert dce(pts, DCE_NOISE_THRESHOLD).tolist() == [0, 199]


def test_step_never_removes_end_points_and_follows_least_relevance() -> None:
    pts = np.array([[0, 0], [1, 0.01], [2, 0], [2, 1], [3, 1.0]])
    ce = CurveEvolution(pts)
    assert len(ce) == 5
    assert ce.min_relevance() == pytest.approx(relevance((0, 0), (1, 0.01), (2, 0)))
    assert ce.step()
    assert ce.removed == [1]
    while ce.step():
        pass
    assert ce.kept_indices().tolist() == [0, 4]
    assert ce.min_relevance() == math.inf
    np.testing.assert_array_equal(ce.points(), pts[[0, 4]])


def test_evolve_to_stops_at_threshold() -> None:
    pts = np.array([[0, 0], [1, 0.01], [2, 0], [2, 1], [3, 1.0]])
    ce = CurveEvolution(pts)
    assert ce.evolve_to(0.5) == 1  # only the tiny bump (relevance ~1e-4) goes
    assert ce.kept_indices().tolist() == [0, 2, 3, 4]
    assert ce.min_relevance() >= 0.5


def test_relevance_evaluations_are_linear_in_n() -> None:
    # Full evolution: k - 2 initial evaluations plus at most 2 per removal, i.e. < 3 k;
    # a naive re-scan after each removal would need ~k^2 / 2.
    rng = np.random.default_rng(1)
    counts = {}
    for k in (500, 2000):
        pts = np.cumsum(rng.normal(size=(k, 2)), axis=0)
        ce = CurveEvolution(pts)
        while ce.step():
            pass
        assert len(ce.removed) == k - 2
        counts[k] = ce.evaluations
        assert ce.evaluations <= 3 * k
    assert counts[2000] / counts[500] < 4.1


def test_dce_is_deterministic_and_validates_input() -> None:
    pts, _ = room_scan(4.0, 3.0, 1.7, 1.2, 400, 0.01, 2)
    assert np.array_equal(dce(pts), dce(pts.copy()))
    with pytest.raises(LocalizationError):
        dce(np.zeros((1, 2)))
    with pytest.raises(LocalizationError, match="non-finite"):
        dce(np.array([[0.0, 0.0], [np.nan, 1.0]]))


def test_refine_vertices_moves_corners_onto_the_fitted_lines() -> None:
    pts, corners = room_scan(4.0, 3.0, 1.7, 1.2, 400, 0.01, 0)
    keep = dce(pts)
    raw = pts[keep]
    ref = refine_vertices(pts, keep)
    assert ref.shape == raw.shape
    err_raw = [np.min(np.hypot(*(raw - c).T)) for c in corners]
    err_ref = [np.min(np.hypot(*(ref - c).T)) for c in corners]
    # measured (seeds 0-2): raw corner errors 0.5-2.4 cm, refined 0.1-0.45 cm
    assert max(err_ref) < 0.01
    assert np.mean(err_ref) < 0.5 * np.mean(err_raw)


def test_refine_vertices_exact_on_noise_free_corner_between_samples() -> None:
    # samples every 3 cm along an L whose corner (1, 0) falls between two samples
    s = np.arange(0.0, 2.0, 0.03) + 0.01
    pts = np.array([[si, 0.0] if si < 1.0 else [1.0, si - 1.0] for si in s])
    keep = dce(pts)
    assert len(keep) == 3
    ref = refine_vertices(pts, keep)
    np.testing.assert_allclose(ref[1], [1.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(ref[[0, 2]], pts[[0, -1]], atol=1e-9)  # ends on their lines


def test_refine_vertices_leaves_far_or_flat_vertices() -> None:
    pts = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.01], [3.0, 0.0]])
    ref = refine_vertices(pts, np.array([0, 2, 3]), min_turn=0.15)
    np.testing.assert_allclose(ref[1], pts[2])  # lines turn by < 0.15 rad: vertex kept
    with pytest.raises(LocalizationError, match="end points"):
        refine_vertices(pts, np.array([1, 3]))


@pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba kernels not installed")
def test_compiled_dce_keeps_the_same_vertices_as_curve_evolution() -> None:
    rng = np.random.default_rng(31)
    for trial in range(500):
        k = int(rng.integers(2, 150))
        if trial % 3 == 0:  # a noisy wall: many near-ties
            p = np.column_stack([np.linspace(0, 3, k), rng.normal(0, 0.01, k)])
        else:
            p = np.cumsum(rng.normal(size=(k, 2)) * rng.uniform(0.001, 0.5), axis=0)
        th = float(rng.uniform(0.001, 0.5))
        ce = CurveEvolution(p)
        ce.evolve_to(th)
        assert np.array_equal(dce(p, th), ce.kept_indices())


@pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba kernels not installed")
def test_compiled_dce_matches_curve_evolution_on_real_groups_and_exact_ties(
    real_scene: Callable,
) -> None:
    """The compiled DCE (an indexed heap, edge lengths kept) removes the same vertices as
    the reference on the grouped returns of real scans and 720-beam map views (setup 2 and
    setup 1), and on polylines of integer points where relevances tie exactly (the lower
    index goes first)."""
    from service.core.shapes.polylines import group_polylines

    groups = []
    for setup_id, scan in ((2, 10), (2, 200), (1, 30)):
        sc = real_scene(setup_id, scan)
        groups += [g.points for g in group_polylines(sc.ranges, sc.angles, min_points=3)]
        n = 720
        ang = -np.pi + (np.arange(n) + 0.5) * (2.0 * np.pi / n)
        r = RayCaster(sc.map_data.segments()).cast(sc.truth[scan], ang, 15.0)
        groups += [g.points for g in group_polylines(r, ang, min_points=3, wrap=True)]
    assert sum(len(g) for g in groups) > 1000
    rng = np.random.default_rng(33)
    for _ in range(300):
        p = rng.integers(0, 4, size=(int(rng.integers(3, 60)), 2)).astype(float)
        keep = np.concatenate(([True], np.any(np.diff(p, axis=0) != 0, axis=1)))
        if keep.sum() >= 2:
            groups.append(p[keep])
    for p in groups:
        for th in (0.02, 0.3):
            ce = CurveEvolution(p)
            ce.evolve_to(th)
            assert np.array_equal(dce(p, th), ce.kept_indices())
