"""Line-matching baseline: split-and-merge extraction, map lines, offset recovery, errors."""

from __future__ import annotations

import math

import numpy as np
import pytest

from service.core.baselines import scan_points
from service.core.baselines.lines import (
    LineConfig,
    LineLocalizer,
    extract_lines,
    fit_line,
    map_lines,
)
from service.core.pose import transform_points
from service.core.types import MapData, wrap_angle
from service.errors import LocalizationError


def _cast(segments: np.ndarray, pose: np.ndarray, angles: np.ndarray, max_range: float):
    """Exact brute-force ray casting for the tests (NaN = no hit)."""
    ox, oy, th = pose
    dx, dy = np.cos(angles + th), np.sin(angles + th)
    x0, y0, x1, y1 = segments.T
    ex, ey = x1 - x0, y1 - y0
    den = dx[:, None] * ey[None, :] - dy[:, None] * ex[None, :]
    wx, wy = x0[None, :] - ox, y0[None, :] - oy
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (wx * ey[None, :] - wy * ex[None, :]) / den
        u = (wx * dy[:, None] - wy * dx[:, None]) / den
    ok = (np.abs(den) > 1e-12) & (t > 0) & (u >= 0) & (u <= 1) & (t <= max_range)
    r = np.where(ok, t, np.inf).min(axis=1)
    return np.where(np.isfinite(r), r, np.nan)


def _square() -> MapData:
    return MapData.from_lists("square", "metric", [[[0, 0], [5, 0], [5, 5], [0, 5], [0, 0]]])


def _room() -> MapData:
    """6 x 4 m room with a notch and a pillar (all directions constrained)."""
    outer = [[0, 0], [3, 0], [6, 0], [6, 2.5], [5, 2.5], [5, 4], [0, 4], [0, 0]]
    pillar = [[2, 1.5], [2.4, 1.5], [2.4, 1.9], [2, 1.9], [2, 1.5]]
    return MapData.from_lists("room", "metric", [outer, pillar])


def _scan(m: MapData, pose: np.ndarray, seed: int, fov: float = np.pi, noise: float = 0.01):
    rng = np.random.default_rng(seed)
    angles = np.linspace(-fov / 2, fov / 2, 361, endpoint=fov < 2 * np.pi)
    r = _cast(m.segments(), pose, angles, 15.0)
    return r + rng.normal(0.0, noise, r.shape), angles


def test_fit_line_normal_form() -> None:
    pts = np.column_stack([np.linspace(0, 2, 20), 1.5 + 0.0 * np.linspace(0, 2, 20)])
    alpha, r, res = fit_line(pts)
    assert math.isclose(r, 1.5, abs_tol=1e-12)
    assert math.isclose(alpha, math.pi / 2, abs_tol=1e-12)
    assert np.max(np.abs(res)) < 1e-12


def test_extraction_finds_the_four_walls_of_a_square_room() -> None:
    m = _square()
    pose = np.array([2.0, 2.6, 0.3])
    ranges, angles = _scan(m, pose, seed=2, fov=2 * np.pi)
    lines = extract_lines(scan_points(ranges, angles), closed=True)
    assert len(lines) == 4
    # Move the lines into the map frame and compare with the four walls (n . p = r).
    walls = {(0.0, 0.0): None, (math.pi / 2, 0.0): None, (0.0, 5.0): None, (math.pi / 2, 5.0): None}
    found = []
    for ln in lines:
        ends = transform_points(pose, np.vstack([ln.p0, ln.p1]))
        alpha, r, _ = fit_line(ends)
        a = float(np.mod(alpha, math.pi))  # undirected normal direction
        if abs(a - math.pi) < 0.1:
            a -= math.pi
        n = np.array([math.cos(a), math.sin(a)])
        r = float(n @ ends[0])
        best = min(walls, key=lambda w: abs(w[0] - a) + abs(w[1] - r))
        assert abs(best[0] - a) < math.radians(0.5), (best, a)
        assert abs(best[1] - r) < 0.01, (best, r)
        assert ln.length > 3.0
        found.append(best)
    assert sorted(found) == sorted(walls)


def test_extraction_drops_short_and_sparse_pieces() -> None:
    rng = np.random.default_rng(0)
    clutter = rng.uniform(-3, 3, size=(40, 2))  # no structure
    assert extract_lines(clutter) == []
    wall = np.column_stack([np.linspace(-1, 1, 50), np.full(50, 2.0)])
    short = np.column_stack([np.full(4, 3.0), np.linspace(0, 0.1, 4)])
    lines = extract_lines(np.vstack([wall, short]), LineConfig(min_points=6))
    assert len(lines) == 1
    assert math.isclose(lines[0].r, 2.0, abs_tol=1e-9)


def test_map_lines_merge_collinear_edges() -> None:
    segs = map_lines(_room())
    # Outer ring: the split bottom edge (0,0)-(3,0)-(6,0) becomes one line; 6 + 4 pillar sides.
    assert len(segs) == 10
    lengths = np.hypot(segs[:, 2] - segs[:, 0], segs[:, 3] - segs[:, 1])
    assert math.isclose(lengths.max(), 6.0)
    ring = MapData.from_lists("r", "metric", [[[1, 0], [2, 0], [2, 2], [0, 2], [0, 0], [1, 0]]])
    assert len(map_lines(ring)) == 4  # merged across the closing vertex


@pytest.mark.parametrize("offset", [(0.10, 0.0, math.radians(3)), (-0.07, 0.07, -0.05)])
def test_line_localizer_recovers_small_offset(offset) -> None:
    m = _room()
    truth = np.array([3.0, 1.0, 0.8])
    ranges, angles = _scan(m, truth, seed=5)
    loc = LineLocalizer(m, truth + np.array(offset))
    est = loc.update(ranges, angles)
    assert np.hypot(*(est.pose[:2] - truth[:2])) < 0.01
    assert abs(wrap_angle(est.pose[2] - truth[2])) < math.radians(0.3)
    assert est.status == "tracking"
    assert 0.5 < est.score <= 1.0
    assert np.allclose(loc.pose, est.pose)


def test_line_localizer_tracks_a_short_motion() -> None:
    m = _room()
    loc = LineLocalizer(m, np.array([1.0, 1.0, 0.0]))
    for i in range(20):
        truth = np.array([1.0 + 0.05 * i, 1.0 + 0.03 * i, 0.03 * i])
        est = loc.update(*_scan(m, truth, seed=i))
    assert np.hypot(*(est.pose[:2] - truth[:2])) < 0.01
    assert abs(wrap_angle(est.pose[2] - truth[2])) < math.radians(0.3)


def test_line_localizer_errors_and_lost() -> None:
    m = _room()
    with pytest.raises(LocalizationError, match="global localisation"):
        LineLocalizer(m, None)
    loc = LineLocalizer(m, np.array([3.0, 1.0, 0.0]))
    with pytest.raises(LocalizationError, match="differ in length"):
        loc.update(np.ones(4), np.zeros(5))
    with pytest.raises(LocalizationError, match="LineConfig"):
        LineLocalizer(m, np.zeros(3), config=object())  # type: ignore[arg-type]
    est = loc.update(np.full(30, np.nan), np.linspace(-1, 1, 30))
    assert est.status == "lost" and est.score == 0.0
    assert np.allclose(est.pose, [3.0, 1.0, 0.0])
    # A scan seen from a pose 2 m away does not match anything within the gates.
    ranges, angles = _scan(m, np.array([3.0, 1.0, 0.0]), seed=1)
    far = LineLocalizer(m, np.array([1.0, 3.0, 2.0]))
    assert far.update(ranges, angles).status == "lost"
