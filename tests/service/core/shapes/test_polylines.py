"""Grouping of range readings into polylines (paper §4.1). Runs in well under a second."""

from __future__ import annotations

import math

import numpy as np
import pytest

from service.core import kernels
from service.core.shapes.polylines import (
    Polyline,
    group_polylines,
    group_spans,
    polylines_of_spans,
    scan_to_points,
)
from service.errors import LocalizationError

ANGLES = np.linspace(-math.pi / 2, math.pi / 2, 361)  # 0.5 deg beams over 180 deg


def wall_ranges(angles: np.ndarray, distance: float, normal: float) -> np.ndarray:
    """Ranges to the infinite line ``x cos(normal) + y sin(normal) = distance`` (NaN behind)."""
    c = np.cos(angles - normal)
    with np.errstate(divide="ignore"):
        r = distance / c
    return np.where(c > 1e-6, r, np.nan)


def test_scan_to_points_keeps_nan_rows_and_frame() -> None:
    pts = scan_to_points(np.array([1.0, np.nan, 2.0]), np.array([0.0, 0.5, math.pi / 2]))
    assert pts.shape == (3, 2)
    np.testing.assert_allclose(pts[0], [1.0, 0.0])
    assert np.all(np.isnan(pts[1]))
    np.testing.assert_allclose(pts[2], [0.0, 2.0], atol=1e-15)  # y is left of the robot


def test_scan_to_points_rejects_mismatched_lengths() -> None:
    with pytest.raises(LocalizationError, match="equal length"):
        scan_to_points(np.ones(3), np.zeros(4))


def test_negative_range_rejected() -> None:
    with pytest.raises(LocalizationError, match=">= 0"):
        group_polylines(np.array([1.0, -1.0]), np.array([0.0, 0.1]))


def test_nan_always_splits() -> None:
    r = np.full(361, 2.0)  # circle of radius 2 m around the sensor: neighbours 1.7 cm apart
    r[100] = np.nan
    pls = group_polylines(r, ANGLES)
    assert [(p.first_beam, p.last_beam) for p in pls] == [(0, 99), (101, 360)]
    assert np.array_equal(pls[1].idx, np.arange(101, 361))


def test_depth_gap_over_10cm_splits_and_under_joins() -> None:
    r = np.full(361, 1.0)
    r[180:] = 1.15  # 15 cm jump at 1 m: threshold is max(0.10, 4 * 1.0 * 0.0087) = 0.10 m
    assert len(group_polylines(r, ANGLES)) == 2
    r[180:] = 1.05  # 5 cm jump: same object
    assert len(group_polylines(r, ANGLES)) == 1


def test_far_depth_jump_still_splits() -> None:
    r = np.full(361, 8.0)
    r[200:] = 8.5  # threshold at 8 m is 4 * 8 * 0.0087 = 0.28 m < 0.5 m
    pls = group_polylines(r, ANGLES)
    assert [(p.first_beam, p.last_beam) for p in pls] == [(0, 199), (200, 360)]


def test_grazing_wall_stays_in_one_piece() -> None:
    # Wall 2 m to the left, running along x; beams 20-70 deg hit it at 20-70 deg incidence,
    # at ranges up to 5.8 m where neighbouring returns are up to 15 cm apart (> 10 cm).
    a = np.deg2rad(np.arange(20.0, 70.01, 0.5))
    r = wall_ranges(a, 2.0, math.pi / 2)
    pts = scan_to_points(r, a)
    gaps = np.hypot(*np.diff(pts, axis=0).T)
    assert gaps.max() > 0.10  # the fixed paper threshold alone would shred it ...
    assert len(group_polylines(r, a, range_factor=0.0, min_points=1)) > 1
    pls = group_polylines(r, a)  # ... the range-adapted one keeps it whole
    assert len(pls) == 1 and len(pls[0]) == a.size
    np.testing.assert_allclose(pls[0].points[:, 1], 2.0, atol=1e-12)


def test_grazing_noisy_wall_in_one_piece() -> None:
    rng = np.random.default_rng(3)
    r = wall_ranges(ANGLES, 2.0, 0.0)
    r[np.abs(ANGLES) > np.deg2rad(70)] = np.nan  # incidence >= 20 deg only, ranges <= 5.8 m
    r = r + rng.normal(0.0, 0.01, r.size)
    pls = group_polylines(r, ANGLES)
    assert len(pls) == 1
    assert pls[0].first_beam == 40 and pls[0].last_beam == 320


def test_min_points_drops_isolated_returns() -> None:
    r = np.full(361, np.nan)
    r[10] = 2.0  # isolated
    r[50:60] = 3.0
    pls = group_polylines(r, ANGLES)
    assert [(p.first_beam, p.last_beam) for p in pls] == [(50, 59)]
    assert len(group_polylines(r, ANGLES, min_points=1)) == 2


def test_wrap_joins_last_and_first_group_in_cyclic_order() -> None:
    n = 360
    a = -math.pi + np.arange(n) * (2 * math.pi / n)
    r = np.full(n, 3.0)
    r[100] = np.nan
    r[200] = np.nan
    plain = group_polylines(r, a)
    assert [(p.first_beam, p.last_beam) for p in plain] == [(0, 99), (101, 199), (201, 359)]
    wrapped = group_polylines(r, a, wrap=True)
    assert [(p.first_beam, p.last_beam) for p in wrapped] == [(101, 199), (201, 99)]
    last = wrapped[-1]
    assert np.array_equal(last.idx, np.r_[201:360, 0:100])
    # consecutive points of the joined polyline are neighbours on the circle (no jump)
    assert np.hypot(*np.diff(last.points, axis=0).T).max() < 0.06
    # full circle with no gap stays one polyline either way
    assert len(group_polylines(np.full(n, 3.0), a, wrap=True)) == 1


def test_wrap_does_not_join_across_a_gap() -> None:
    n = 360
    a = -math.pi + np.arange(n) * (2 * math.pi / n)
    r = np.full(n, 3.0)
    r[180:] = 4.0  # last beam at 4 m, first at 3 m: 1 m apart
    pls = group_polylines(r, a, wrap=True)
    assert [(p.first_beam, p.last_beam) for p in pls] == [(0, 179), (180, 359)]


def test_polyline_length_and_angular_size() -> None:
    a = np.deg2rad(np.arange(-10.0, 10.01, 0.5))
    r = wall_ranges(a, 2.0, 0.0)  # wall at x = 2
    (pl,) = group_polylines(r, a)
    assert isinstance(pl, Polyline)
    assert pl.length == pytest.approx(2 * 2.0 * math.tan(math.radians(10)), rel=1e-9)
    assert pl.angular_size == pytest.approx(math.radians(20), rel=1e-9)
    assert pl.bearing_start == pytest.approx(math.radians(-10))
    assert pl.bearing_end == pytest.approx(math.radians(10))
    sub = pl.subset(np.array([0, len(pl) - 1]))
    assert len(sub) == 2 and sub.length == pytest.approx(pl.length)


def test_angular_size_across_the_seam() -> None:
    n = 360
    a = -math.pi + np.arange(n) * (2 * math.pi / n)
    r = np.full(n, np.nan)
    r[:11] = 2.0  # bearings -180 .. -170 deg
    r[-10:] = 2.0  # bearings 170 .. 179 deg
    (pl,) = group_polylines(r, a, wrap=True)
    assert pl.angular_size == pytest.approx(math.radians(20), abs=1e-9)


def test_polylines_are_hashable_by_identity() -> None:
    pls = group_polylines(np.full(361, 2.0), ANGLES)
    assert len({pls[0], pls[0]}) == 1
    assert pls[0] == pls[0]
    assert pls[0] != group_polylines(np.full(361, 2.0), ANGLES)[0]


def _rough_scans(seed: int, count: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Smoothed random ranges with holes over random fields of view: walls, corners, depth
    jumps of every size and grazing stretches."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(count):
        n = int(rng.integers(20, 400))
        a = np.linspace(-2.0, 2.0, n) if k % 2 else np.sort(rng.uniform(-3.1, 3.1, n))
        r = np.convolve(rng.uniform(0.1, 8.0, n), np.ones(15) / 15, "same")
        r[rng.random(n) < 0.1] = np.nan
        out.append((r, a))
    return out


@pytest.mark.parametrize("numba", [True, False])
def test_group_spans_are_the_groups_of_group_polylines(
    numba: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    if numba and not kernels.HAVE_NUMBA:
        pytest.skip("numba kernels not installed")
    monkeypatch.setattr(kernels, "HAVE_NUMBA", numba)
    groups = 0
    for r, a in _rough_scans(1, 150):
        ref = [g for g in group_polylines(r, a, 0.1, 4.0, 3) if g.length >= 0.2]
        pts, spans = group_spans(r, a, 0.1, 4.0, 3, 0.2)
        assert [(g.first_beam, g.last_beam) for g in ref] == [tuple(s) for s in spans.tolist()]
        for g, h in zip(ref, polylines_of_spans(pts, spans), strict=True):
            np.testing.assert_array_equal(g.points, h.points)
            np.testing.assert_array_equal(g.idx, h.idx)
            assert (g.bearing_start, g.bearing_end) == (h.bearing_start, h.bearing_end)
        groups += len(ref)
    assert groups > 1000  # the scans hold many groups, dropped ones among them
    with pytest.raises(LocalizationError):
        group_spans(np.array([1.0, -1.0]), np.array([0.0, 0.1]))
